//! Tables that compose (issue 15): which tables the PLC applies now, and what a table made
//! from a run taken under compensation must be.
//!
//! A run measured while the PLC applied a table sees only that table's residual. Published
//! as it is, the residual would replace the table and undo the compensation. So:
//! - every run records the tables active when it started ([`active_tables`], from the PLC
//!   read back and the store's publications; `store::RunTables`);
//! - a table generated from such a run is the active table plus the residual, on the active
//!   table's grid ([`compose_stored`]), and says so ([`Base`](super::stored::Base));
//! - publishing refuses a table whose base is not what the PLC applies now, and a table from
//!   a run under compensation that is not composed (the residual alone) ([`publishable`]).
//!
//! The PLC protocol has one staging area and one active sequence (plc-maps/README.md): the
//! table published last is read back with its sequence and CRC; the others the PLC applies
//! are known from the store's record of what it accepted, and are marked so.

use super::stored::{StoredTable, kind_from_name};
use crate::comp::table::compose;
use crate::comp::{CompTable, TableValues};
use crate::plc::table::{RawHeader, Reject, TableDirection};
use crate::plc::{PlcStatus, PlcTable};
use crate::store::{
    ActiveTable, PublicationOutcome, PublicationRecord, RunId, RunState, RunTables, Store, TableId,
    TableRecord,
};
use std::collections::BTreeMap;

/// Whether run `run` may give a compensation table, and what the PLC applied while it ran:
/// it must be finished, with no flagged capture left open (`store::flags`), and with the
/// tables active during it recorded and known, since a table made from a run taken under
/// compensation is the residual on top of them. `residual_only` (asked for by name) lets a
/// run without that record give its residual; `None` then.
pub fn usable(store: &Store, run: RunId, residual_only: bool) -> Result<Option<RunTables>, String> {
    let rec = store.run(run).map_err(|e| e.to_string())?;
    if rec.state != RunState::Finished {
        return Err(format!(
            "run {run} is {}: tables come from finished runs only",
            rec.state
        ));
    }
    if let Some(why) = store.open_flags(run).map_err(|e| e.to_string())? {
        return Err(why);
    }
    match store.run_tables(run).map_err(|e| e.to_string())? {
        Some(t) if t.known => Ok(Some(t)),
        _ if residual_only => Ok(None),
        Some(t) => Err(format!(
            "run {run} started when the PLC could not be read ({}): the tables it applied are unknown, so a table from it could be the residual on top of one of them; measure again, or ask for the residual by name (--residual-only)",
            t.source
        )),
        None => Err(format!(
            "run {run} has no record of the tables the PLC applied while it ran (it was not measured by the service): a table from it could be the residual on top of one of them; measure again through the service, or ask for the residual by name (--residual-only)"
        )),
    }
}

/// The tables `status` (and the staging area `staged`, when it could be read) say the PLC at
/// `target` applies now. Known only when the PLC is empty or its active sequence is one the
/// store recorded as accepted by `target`; then, for each kind and axis, the last table it
/// accepted up to that publication. The one whose sequence and CRC the staging area shows is
/// marked `read_back`.
pub fn active_tables(
    status: &PlcStatus,
    staged: Option<(&RawHeader, Option<&Reject>)>,
    tables: &[TableRecord],
    pubs: &[PublicationRecord],
    target: &str,
    unix_us: i64,
) -> RunTables {
    let unknown = |why: String| RunTables {
        unix_us,
        known: false,
        source: why,
        tables: Vec::new(),
    };
    let active = status.active_sequence;
    if active == 0 {
        return RunTables {
            unix_us,
            known: true,
            source: format!("{target}: empty (active sequence 0)"),
            tables: Vec::new(),
        };
    }
    let accepted: Vec<&PublicationRecord> = pubs
        .iter()
        .filter(|p| {
            p.publication.target == target && p.publication.outcome == PublicationOutcome::Accepted
        })
        .collect();
    let Some(last) = accepted
        .iter()
        .rposition(|p| p.publication.sequence == active)
    else {
        return unknown(format!(
            "{target} applies sequence {active}, which the store has not recorded as accepted by it"
        ));
    };
    let mut by_kind: BTreeMap<(String, String), ActiveTable> = BTreeMap::new();
    for p in &accepted[..=last] {
        let Some(t) = tables.iter().find(|t| t.id == p.publication.table) else {
            continue;
        };
        by_kind.insert(
            (t.entry.kind.clone(), t.entry.axis.clone()),
            ActiveTable {
                kind: t.entry.kind.clone(),
                axis: t.entry.axis.clone(),
                table: Some(t.id),
                sequence: p.publication.sequence,
                crc: t.entry.crc,
                read_back: false,
            },
        );
    }
    let mut out: Vec<ActiveTable> = by_kind.into_values().collect();
    out.sort_by_key(|a| a.sequence);
    let mut source = format!(
        "{target}: active sequence {active}; the others from the store's accepted publications"
    );
    if let Some((h, reject)) = staged
        && h.sequence == active
    {
        let latest = out.iter_mut().find(|a| a.sequence == active);
        match (latest, reject) {
            (Some(a), None) if a.crc == h.crc => {
                a.read_back = true;
                source = format!(
                    "{target}: sequence {active} read back (CRC 0x{:08X}); the others from the store's accepted publications",
                    h.crc
                );
            }
            (Some(a), _) => {
                return unknown(format!(
                    "{target}: the staging area for active sequence {active} (CRC 0x{:08X}) is not table {} (CRC 0x{:08X}){}",
                    h.crc,
                    a.table.map_or(0, |t| t.0),
                    a.crc,
                    reject.map_or_else(String::new, |r| format!(", and fails its check ({r})"))
                ));
            }
            (None, _) => {}
        }
    }
    RunTables {
        unix_us,
        known: true,
        source,
        tables: out,
    }
}

/// A stored table as a `CompTable` on its own (the PLC's) grid.
pub fn grid_table(s: &StoredTable) -> Result<CompTable, String> {
    let t = s.plc_table()?;
    let positions_mm = t.positions();
    let values = match (t.direction, &t.down_mm) {
        (TableDirection::Bidirectional, Some(down)) => TableValues::Bidirectional {
            up: t.values_mm.clone(),
            down: down.clone(),
        },
        _ => TableValues::Single {
            values: t.values_mm.clone(),
            backlash_mm: None,
        },
    };
    Ok(CompTable {
        kind: kind_from_name(&s.kind).ok_or_else(|| format!("kind {:?}", s.kind))?,
        name: s.name.clone(),
        base_axis: s.base_axis,
        comp_axis: s.axis,
        reference_mm: s.reference_mm,
        positions_mm,
        values,
    })
}

/// The active table `base` plus the `residual` measured under it, as a PLC table on
/// `base`'s grid (start, interval and point count unchanged).
pub fn compose_stored(base: &StoredTable, residual: &CompTable) -> Result<PlcTable, String> {
    let c = compose(&grid_table(base)?, residual).map_err(|e| e.to_string())?;
    let b = base.plc_table()?;
    let (direction, values_mm, down_mm) = match c.values {
        TableValues::Single { values, .. } => (TableDirection::Both, values, None),
        TableValues::Bidirectional { up, down } => (TableDirection::Bidirectional, up, Some(down)),
    };
    Ok(PlcTable {
        direction,
        values_mm,
        down_mm,
        ..b
    })
}

/// Whether table `id` (stored as `s`, generated from a run that ran under `during`) may be
/// published while the PLC applies `now`: `Err` with the reason when it is the residual alone
/// (the run ran under a table of its kind and it is not composed), or composed on a table the
/// PLC no longer applies.
pub fn publishable(
    id: TableId,
    s: &StoredTable,
    source_run: Option<i64>,
    during: Option<&RunTables>,
    now: &RunTables,
) -> Result<(), String> {
    let what = format!("{} table {id} ({} {})", s.kind, s.name, s.axis);
    match &s.base {
        None => {
            if let (Some(run), Some(d)) = (source_run, during)
                && let Some(a) = d.find(&s.kind, &s.axis.to_string())
            {
                return Err(format!(
                    "{what} is the residual alone: run {run} was measured while the PLC applied {} (sequence {}), and this table is not composed with it; publishing it would replace that compensation by what it left. Generate the tables of run {run} again (table generate --run {run}): they are the active table plus the residual",
                    a.table
                        .map_or_else(|| "a table".into(), |t| format!("table {t}")),
                    a.sequence
                ));
            }
            Ok(())
        }
        Some(base) => {
            if !now.known {
                return Err(format!(
                    "{what} is composed on {}; what the PLC applies now is unknown ({}), so it cannot be checked: read the PLC (table status) and try again",
                    base.describe(),
                    now.source
                ));
            }
            let b = &base.active;
            match now.find(&b.kind, &b.axis) {
                Some(a) if a.sequence == b.sequence && a.crc == b.crc => Ok(()),
                Some(a) => Err(format!(
                    "{what} is composed on {}, but the PLC now applies {} (sequence {}, CRC 0x{:08X}) for {} {}: its base is not what the PLC holds. Measure again under the active table and generate from that run",
                    base.describe(),
                    a.table
                        .map_or_else(|| "another table".into(), |t| format!("table {t}")),
                    a.sequence,
                    a.crc,
                    b.kind,
                    b.axis
                )),
                None => Err(format!(
                    "{what} is composed on {}, but the PLC now applies no {} table for {}: its base is not what the PLC holds. Measure again and generate from that run",
                    base.describe(),
                    b.kind,
                    b.axis
                )),
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::plc::StatusCode;
    use crate::service::stored::Base;
    use crate::store::{Publication, TableEntry};

    pub(crate) fn header(sequence: u32, crc: u32) -> RawHeader {
        RawHeader {
            kind: 1,
            axis: 2,
            base_axis: 2,
            direction: 3,
            points: 11,
            unit: 100,
            start_mm: 0.0,
            interval_mm: 10.0,
            sequence,
            crc,
        }
    }

    fn status(active: u32) -> PlcStatus {
        PlcStatus {
            ready: 1,
            heartbeat: 3,
            status: StatusCode::Accepted,
            error_code: 0,
            status_sequence: active,
            active_sequence: active,
        }
    }

    fn table(id: i64, kind: &str, axis: &str, crc: u32) -> TableRecord {
        TableRecord {
            id: TableId(id),
            entry: TableEntry {
                kind: kind.into(),
                axis: axis.into(),
                direction: None,
                generated_us: 0,
                source_run: Some(crate::store::RunId(1)),
                values: serde_json::json!({}),
                crc,
            },
        }
    }

    fn accepted(id: i64, table: i64, sequence: u32, target: &str) -> PublicationRecord {
        PublicationRecord {
            id,
            publication: Publication {
                table: TableId(table),
                target: target.into(),
                sequence,
                outcome: PublicationOutcome::Accepted,
                unix_us: 0,
            },
        }
    }

    #[test]
    fn the_active_tables_per_kind_and_axis_from_the_read_back_and_the_store() {
        let tables = [
            table(1, "positioning", "X", 0x11),
            table(2, "straightness", "Y", 0x22),
            table(3, "positioning", "X", 0x33),
        ];
        let pubs = [
            accepted(1, 1, 1, "plc"),
            accepted(2, 2, 2, "plc"),
            accepted(3, 3, 3, "other plc"),
            accepted(4, 3, 4, "plc"),
        ];
        let a = |active: u32, staged: Option<(&RawHeader, Option<&Reject>)>| {
            active_tables(&status(active), staged, &tables, &pubs, "plc", 7)
        };
        assert!(a(0, None).known && a(0, None).tables.is_empty());
        // Sequence 4 replaced table 1 by table 3 for positioning X; table 2 stays.
        let h = header(4, 0x33);
        let now = a(4, Some((&h, None)));
        assert!(now.known, "{now:?}");
        let got: Vec<_> = now
            .tables
            .iter()
            .map(|t| (t.table, t.sequence, t.read_back))
            .collect();
        assert_eq!(
            got,
            [(Some(TableId(2)), 2, false), (Some(TableId(3)), 4, true)]
        );
        assert!(
            now.source.contains("sequence 4 read back"),
            "{}",
            now.source
        );
        // Sequence 2 was active: only what was accepted up to it.
        let then = a(2, None);
        assert_eq!(then.tables.len(), 2);
        assert_eq!(
            then.find("positioning", "X").and_then(|t| t.table),
            Some(TableId(1))
        );
        // A sequence the store did not record, or a staging area that is not the table.
        let u = a(9, None);
        assert!(!u.known && u.source.contains("sequence 9"), "{}", u.source);
        let wrong = header(4, 0x99);
        let u = a(4, Some((&wrong, None)));
        assert!(
            !u.known && u.source.contains("is not table 3"),
            "{}",
            u.source
        );
    }

    #[test]
    fn the_residual_alone_and_a_stale_base_are_refused() {
        let m = crate::plc::CncMap::generic().unwrap();
        let comp = CompTable {
            kind: crate::comp::TableKind::Positioning,
            name: "EXX".into(),
            base_axis: crate::comp::MachineAxis::X,
            comp_axis: crate::comp::MachineAxis::X,
            reference_mm: 0.0,
            positions_mm: vec![0.0, 10.0, 20.0],
            values: TableValues::Single {
                values: vec![0.0, 0.001, 0.002],
                backlash_mm: None,
            },
        };
        let t = PlcTable::from_comp(&comp, &m, Some(10.0)).unwrap();
        let mut s = StoredTable::new(&m, &t, &comp);
        let active = ActiveTable {
            kind: "positioning".into(),
            axis: "X".into(),
            table: Some(TableId(1)),
            sequence: 1,
            crc: 0x11,
            read_back: true,
        };
        let with = |tables: Vec<ActiveTable>| RunTables {
            unix_us: 0,
            known: true,
            source: "plc".into(),
            tables,
        };
        let during = with(vec![active.clone()]);
        let none = with(vec![]);
        // A measured table from a run without compensation: published over anything.
        assert!(publishable(TableId(4), &s, Some(1), Some(&none), &during).is_ok());
        let e = publishable(TableId(4), &s, Some(3), Some(&during), &during).unwrap_err();
        assert!(
            e.contains("is the residual alone") && e.contains("run 3"),
            "{e}"
        );
        // Composed on what the PLC holds: fine; on anything else: refused.
        s.base = Some(Base {
            active: active.clone(),
            run_id: 3,
        });
        assert!(publishable(TableId(4), &s, Some(3), Some(&during), &during).is_ok());
        let moved = with(vec![ActiveTable {
            table: Some(TableId(5)),
            sequence: 4,
            crc: 0x55,
            ..active
        }]);
        let e = publishable(TableId(4), &s, Some(3), Some(&during), &moved).unwrap_err();
        assert!(
            e.contains("its base is not what the PLC holds") && e.contains("table 5 (sequence 4"),
            "{e}"
        );
        let e = publishable(TableId(4), &s, Some(3), Some(&during), &none).unwrap_err();
        assert!(e.contains("applies no positioning table for X"), "{e}");
        // Composition keeps the active table's grid.
        let residual = CompTable {
            values: TableValues::Single {
                values: vec![0.0, 0.0005, 0.0005],
                backlash_mm: None,
            },
            ..comp
        };
        let c = compose_stored(&s, &residual).unwrap();
        assert_eq!((c.start_mm, c.interval_mm), (t.start_mm, t.interval_mm));
        assert_eq!(c.values_mm.len(), t.values_mm.len());
        assert!((c.values_mm[2] - 0.0025).abs() < 1e-12, "{:?}", c.values_mm);
    }
}
