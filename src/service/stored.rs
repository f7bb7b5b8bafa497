//! A compensation table as the store keeps it (`tables.values_json`): the table as published
//! into the PLC (fitted to the CNC map's grid), the table as measured beside it, and, for a
//! composed table (issue 15), the table it was built on. Read by the tables task, the
//! composition rules, the export and the console; one reader for the format.

use crate::comp::{CompTable, MachineAxis, TableKind};
use crate::plc::table::TableDirection;
use crate::plc::{CncMap, PlcTable};
use crate::run::Direction;
use crate::store::{ActiveTable, RunId, TableEntry, TableRecord};
use serde::{Deserialize, Serialize};

/// The `format` of a stored table's values.
pub const FORMAT: &str = "axiscomp-plc-table/1";

/// What a composed table was built on: the active table during the run, and the run.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Base {
    /// The table that was active (kind, axis, stored id, sequence, CRC).
    pub active: ActiveTable,
    /// The run whose residual was added.
    pub run_id: i64,
}

impl Base {
    /// "table 3 (sequence 4, CRC 0x…) + the residual of run 2".
    pub fn describe(&self) -> String {
        let a = &self.active;
        let id = a
            .table
            .map_or_else(|| "the PLC's table".into(), |t| format!("table {t}"));
        format!(
            "{id} (sequence {}, CRC 0x{:08X}) + the residual measured by run {}",
            a.sequence, a.crc, self.run_id
        )
    }
}

/// A table's `values_json` in the store: the table as published, and as measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredTable {
    /// [`FORMAT`].
    pub format: String,
    /// ISO 230-1 name ("EYY", "EXY").
    pub name: String,
    /// The CNC map it was fitted to (its `name`).
    pub map: String,
    /// "positioning", "straightness" or "abbe".
    pub kind: String,
    /// The axis the values act on, and the one whose position indexes them.
    pub axis: MachineAxis,
    pub base_axis: MachineAxis,
    /// "both", "+", "-" or "bidirectional" (+ profile in `values_mm`, − in `down_mm`).
    pub direction: String,
    pub start_mm: f64,
    pub interval_mm: f64,
    /// e = measured − nominal (mm) per point.
    pub values_mm: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub down_mm: Option<Vec<f64>>,
    /// Where the values are zero (mm).
    pub reference_mm: f64,
    /// The table as measured (`comp::CompTable`), before fitting to the PLC's grid; for a
    /// composed table, the residual the run measured.
    #[serde(default)]
    pub measured: serde_json::Value,
    /// Composed (issue 15): the table active during the run, which these values include.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base: Option<Base>,
}

pub(crate) fn direction_name(d: TableDirection) -> &'static str {
    match d {
        TableDirection::Both => "both",
        TableDirection::Positive => "+",
        TableDirection::Negative => "-",
        TableDirection::Bidirectional => "bidirectional",
    }
}

pub(crate) fn direction_from_name(s: &str) -> Option<TableDirection> {
    Some(match s {
        "both" => TableDirection::Both,
        "+" => TableDirection::Positive,
        "-" => TableDirection::Negative,
        "bidirectional" => TableDirection::Bidirectional,
        _ => return None,
    })
}

pub(crate) fn kind_from_name(s: &str) -> Option<TableKind> {
    Some(match s {
        "positioning" => TableKind::Positioning,
        "straightness" => TableKind::Straightness,
        "abbe" => TableKind::Abbe,
        _ => return None,
    })
}

impl StoredTable {
    pub fn new(map: &CncMap, t: &PlcTable, measured: &CompTable) -> StoredTable {
        StoredTable {
            format: FORMAT.into(),
            name: measured.name.clone(),
            map: map.name.clone(),
            kind: t.kind.name().into(),
            axis: t.axis,
            base_axis: t.base_axis,
            direction: direction_name(t.direction).into(),
            start_mm: t.start_mm,
            interval_mm: t.interval_mm,
            values_mm: t.values_mm.clone(),
            down_mm: t.down_mm.clone(),
            reference_mm: measured.reference_mm,
            measured: serde_json::to_value(measured).unwrap_or_default(),
            base: None,
        }
    }

    /// The store's row for this table as `t` was fitted (its kind, axis and direction), made at
    /// `generated_us` from run `source_run`, its payload's CRC `crc` as published.
    pub fn entry(
        &self,
        t: &PlcTable,
        crc: u32,
        source_run: Option<RunId>,
        generated_us: i64,
    ) -> Result<TableEntry, serde_json::Error> {
        Ok(TableEntry {
            kind: t.kind.name().into(),
            axis: t.axis.letter().into(),
            direction: match t.direction {
                TableDirection::Positive => Some(Direction::Up),
                TableDirection::Negative => Some(Direction::Down),
                _ => None,
            },
            generated_us,
            source_run,
            values: serde_json::to_value(self)?,
            crc,
        })
    }

    /// What the values are: "composed: …", or "measured" (with why nothing was composed).
    pub fn composition(&self) -> String {
        match &self.base {
            Some(b) => format!("composed: {}", b.describe()),
            None => "measured".into(),
        }
    }

    /// From a stored table's values.
    pub fn from_record(r: &TableRecord) -> Result<StoredTable, String> {
        let not_ours = |why: String| {
            format!(
                "table {} was not generated for a PLC ({why}); generate one with table_generate",
                r.id
            )
        };
        let s: StoredTable =
            serde_json::from_value(r.entry.values.clone()).map_err(|e| not_ours(e.to_string()))?;
        if s.format != FORMAT {
            return Err(not_ours(format!("format {:?}", s.format)));
        }
        Ok(s)
    }

    /// The table as the PLC protocol carries it.
    pub fn plc_table(&self) -> Result<PlcTable, String> {
        Ok(PlcTable {
            kind: kind_from_name(&self.kind).ok_or_else(|| format!("kind {:?}", self.kind))?,
            axis: self.axis,
            base_axis: self.base_axis,
            direction: direction_from_name(&self.direction)
                .ok_or_else(|| format!("direction {:?}", self.direction))?,
            start_mm: self.start_mm,
            interval_mm: self.interval_mm,
            values_mm: self.values_mm.clone(),
            down_mm: self.down_mm.clone(),
        })
    }

    /// Smallest and largest value over both profiles (µm).
    pub fn range_um(&self) -> (f64, f64) {
        self.values_mm
            .iter()
            .chain(self.down_mm.iter().flatten())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v * 1e3), hi.max(v * 1e3))
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::comp;
    use crate::store::TableId;

    fn record(id: i64) -> TableRecord {
        TableRecord {
            id: TableId(id),
            entry: TableEntry {
                kind: "positioning".into(),
                axis: "Y".into(),
                direction: None,
                generated_us: 0,
                source_run: None,
                values: serde_json::json!({}),
                crc: 0,
            },
        }
    }

    #[test]
    fn stored_tables_round_trip() {
        let m = CncMap::generic().unwrap();
        let comp = CompTable {
            kind: TableKind::Positioning,
            name: "EYY".into(),
            base_axis: MachineAxis::Y,
            comp_axis: MachineAxis::Y,
            reference_mm: 0.0,
            positions_mm: vec![0.0, 10.0, 20.0],
            values: comp::TableValues::Single {
                values: vec![0.0, 0.002, -0.001],
                backlash_mm: Some(0.003),
            },
        };
        let t = PlcTable::from_comp(&comp, &m, None).unwrap();
        let s = StoredTable::new(&m, &t, &comp);
        let rec = TableRecord {
            id: TableId(3),
            entry: TableEntry {
                values: serde_json::to_value(&s).unwrap(),
                ..record(3).entry
            },
        };
        let back = StoredTable::from_record(&rec).unwrap();
        assert_eq!(back, s);
        assert_eq!(back.plc_table().unwrap(), t);
        assert_eq!(back.direction, "bidirectional");
        let (lo, hi) = back.range_um();
        assert!(
            (lo + 1.0).abs() < 1e-9 && (hi - 5.0).abs() < 1e-9,
            "{lo} {hi}"
        );
        let e = StoredTable::from_record(&record(4)).unwrap_err();
        assert!(e.contains("table 4 was not generated for a PLC"), "{e}");
    }
}
