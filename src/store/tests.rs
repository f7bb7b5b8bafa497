use super::*;
use crate::calibrate::file::{CalibrationFile, LinearSection, Meta};
use crate::run::{Capture, Direction, TargetKey};
use crate::track::{HandoverKind, HandoverRecord};
use crate::units::Errors6;
use serde_json::json;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A database path in a fresh directory, removed (with -wal and -shm) on drop.
struct TempDb {
    dir: PathBuf,
    path: PathBuf,
}

impl TempDb {
    fn new(name: &str) -> TempDb {
        static N: AtomicUsize = AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!(
            "axiscomp-store-{}-{}-{name}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("store.sqlite");
        TempDb { dir, path }
    }
}

impl Drop for TempDb {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn new_run() -> NewRun {
    NewRun {
        axis: "Y".into(),
        plan: json!({"targets_mm": [0.0, 100.0, 200.0], "runs": 5}),
        config: json!({"capture": {"mode": "stability"}}),
        calibration: None,
        notes: String::new(),
    }
}

fn capture(run: u32, target_index: u32, direction: Direction, seed: f64) -> Capture {
    Capture {
        run,
        target_index,
        target_mm: 100.0 * f64::from(target_index),
        direction,
        errors: Errors6::from_array([1e-3 * seed, -2e-3, 3.3e-4, 1e-6 * seed, -2e-6, 5e-7]),
        frame_sd: Errors6::from_array([1e-4, 2e-4, 3e-4, 1e-7, 2e-7, 3e-7]),
        u: Errors6::from_array([1e-5, 2e-5, 3e-5, 1e-8, 2e-8, 3e-8]),
        frames: 200,
        material_c: Some(20.25),
        air_c: if seed > 1.0 { None } else { Some(21.5) },
        unix_us: 1_700_000_000_000_000 + i64::from(target_index),
    }
}

fn handover(unix_us: i64) -> HandoverRecord {
    HandoverRecord {
        unix_us,
        kind: HandoverKind::Overlap,
        before: [2.5, 0.01],
        after: [-2.5, 0.012],
        n_before: 50,
        n_after: 51,
        frame_sd: [1e-3, 1.5e-3],
        encoder_before: 10.0,
        encoder_after: 15.0,
        delta: [5.0002, -0.002],
        variance: [4e-8, 5e-8],
    }
}

fn calibration_text(hash: &str) -> String {
    CalibrationFile {
        meta: Meta {
            format: crate::calibrate::file::FORMAT,
            created: "2025-03-01T10:00:00Z".into(),
            layout: "reference".into(),
            layout_hash: hash.into(),
            poses: 200,
            fit_poses: 150,
            holdout_poses: 50,
            travel_mm: [0.0, 100.0],
            noise_um: [1.0; 6],
        },
        linear: LinearSection {
            rank: 7,
            rcond: 1e-10,
            condition_number: 5.6,
            ref_travel_mm: 0.0,
            ref_follower_mm: 0.0,
            residual_rms_um: [1.0, 1.1, 1.2, 1.3, 1.4, 1.5],
            holdout_rms: Some([0.5, 1.2, 0.55, 0.3, 1.4, 0.3]),
            singular_values: vec![1.0; 7],
            offset_um: [0.0; 6],
            beta: [[0.0; 6]; 6],
        },
        model: None,
    }
    .to_toml()
}

#[test]
fn open_sets_wal_full_sync_foreign_keys_and_schema() {
    let db = TempDb::new("pragmas");
    let store = Store::open(&db.path).unwrap();
    let mode: String = store
        .conn
        .pragma_query_value(None, "journal_mode", |r| r.get(0))
        .unwrap();
    assert_eq!(mode, "wal");
    let sync: i64 = store
        .conn
        .pragma_query_value(None, "synchronous", |r| r.get(0))
        .unwrap();
    assert_eq!(sync, 2, "synchronous must be FULL (2)");
    let fk: i64 = store
        .conn
        .pragma_query_value(None, "foreign_keys", |r| r.get(0))
        .unwrap();
    assert_eq!(fk, 1);
    let app: i32 = store
        .conn
        .pragma_query_value(None, "application_id", |r| r.get(0))
        .unwrap();
    assert_eq!(app, schema::APPLICATION_ID);
    assert_eq!(store.schema_version().unwrap(), schema::LATEST);
    assert_eq!(store.integrity_check().unwrap(), ["ok"]);
    assert!(!store.is_read_only());
    assert_eq!(store.path(), db.path.as_path());
}

#[test]
fn reopening_keeps_data_and_does_not_migrate_again() {
    let db = TempDb::new("reopen");
    let id = {
        let mut store = Store::open(&db.path).unwrap();
        store.create_run(&new_run()).unwrap()
    };
    let store = Store::open(&db.path).unwrap();
    assert_eq!(store.schema_version().unwrap(), schema::LATEST);
    assert_eq!(store.run(id).unwrap().axis, "Y");
}

#[test]
fn run_lifecycle() {
    let db = TempDb::new("runs");
    let mut store = Store::open(&db.path).unwrap();
    let a = store.create_run(&new_run()).unwrap();
    let b = store
        .create_run(&NewRun {
            axis: "X".into(),
            notes: "second".into(),
            ..new_run()
        })
        .unwrap();
    let ra = store.run(a).unwrap();
    assert_eq!(ra.state, RunState::Planned);
    assert_eq!(ra.plan, new_run().plan);
    assert_eq!(ra.config, new_run().config);
    assert_eq!(ra.created_us, ra.updated_us);
    assert!(ra.created_us > 1_600_000_000_000_000);

    store.set_run_state(a, RunState::Running).unwrap();
    store.set_run_notes(a, "bearing noise at 150 mm").unwrap();
    let ra = store.run(a).unwrap();
    assert_eq!(ra.state, RunState::Running);
    assert_eq!(ra.notes, "bearing noise at 150 mm");
    assert!(ra.updated_us >= ra.created_us);
    assert_eq!(
        store
            .runs_in_state(RunState::Running)
            .unwrap()
            .iter()
            .map(|r| r.id)
            .collect::<Vec<_>>(),
        [a]
    );
    let all = store.list_runs().unwrap();
    assert_eq!(all.iter().map(|r| r.id).collect::<Vec<_>>(), [a, b]);
    assert_eq!(all[1].notes, "second");

    store.set_run_state(a, RunState::Aborted).unwrap();
    store.set_run_state(a, RunState::Running).unwrap(); // resumed
    store.set_run_state(a, RunState::Finished).unwrap();
    let err = store.set_run_state(a, RunState::Running).unwrap_err();
    assert!(matches!(
        err,
        StoreError::StateTransition {
            from: RunState::Finished,
            to: RunState::Running,
            ..
        }
    ));
    assert!(matches!(
        store.set_run_state(b, RunState::Finished),
        Err(StoreError::StateTransition { .. })
    ));
    assert_eq!(store.run(a).unwrap().state, RunState::Finished);
    assert!(matches!(
        store.run(RunId(999)),
        Err(StoreError::NoSuchRun(RunId(999)))
    ));
    assert!(matches!(
        store.set_run_state(RunId(999), RunState::Running),
        Err(StoreError::NoSuchRun(_))
    ));
    assert!(matches!(
        store.set_run_notes(RunId(999), "x"),
        Err(StoreError::NoSuchRun(_))
    ));
    assert!(matches!(
        store.create_run(&NewRun {
            calibration: Some(CalibrationId(42)),
            ..new_run()
        }),
        Err(StoreError::NoSuchCalibration(CalibrationId(42)))
    ));
}

#[test]
fn state_rules() {
    use RunState::*;
    assert!(Planned.may_become(Running));
    assert!(Running.may_become(Running));
    assert!(Failed.may_become(Running));
    assert!(!Finished.may_become(Aborted));
    assert!(!Running.may_become(Planned));
    assert!(!Aborted.may_become(Finished));
    for s in RunState::ALL {
        assert_eq!(RunState::parse(s.as_str()), Some(s));
    }
}

#[test]
fn captures_are_stored_exactly_once_and_round_trip() {
    let db = TempDb::new("captures");
    let mut store = Store::open(&db.path).unwrap();
    let run = store.create_run(&new_run()).unwrap();
    let other = store.create_run(&new_run()).unwrap();
    let c1 = capture(1, 0, Direction::Up, 1.0);
    let c2 = capture(1, 1, Direction::Up, 2.0);
    let c3 = capture(1, 1, Direction::Down, 3.0);
    assert!(store.insert_capture(run, &c1).unwrap());
    assert!(store.insert_capture(run, &c2).unwrap());
    assert!(store.insert_capture(run, &c3).unwrap());
    // Offered again (a resumed run), even with other values: the first is kept.
    assert!(!store.insert_capture(run, &c2).unwrap());
    assert!(
        !store
            .insert_capture(run, &capture(1, 1, Direction::Up, 9.0))
            .unwrap()
    );
    // The same key in another run is another capture.
    assert!(store.insert_capture(other, &c2).unwrap());

    assert_eq!(store.captures(run).unwrap(), [c1, c2, c3]);
    assert_eq!(store.captures(other).unwrap(), [c2]);
    let keys = store.completed_keys(run).unwrap();
    assert_eq!(
        keys.into_iter().collect::<Vec<_>>(),
        [
            TargetKey::of(&c1),
            TargetKey {
                run: 1,
                target_index: 1,
                direction: Direction::Up
            },
            TargetKey::of(&c3),
        ]
    );
    assert!(matches!(
        store.insert_capture(RunId(77), &c1),
        Err(StoreError::NoSuchRun(RunId(77)))
    ));
}

#[test]
fn invalid_captures_are_refused_before_sql() {
    let db = TempDb::new("invalid");
    let mut store = Store::open(&db.path).unwrap();
    let run = store.create_run(&new_run()).unwrap();
    let mut c = capture(1, 0, Direction::Up, 1.0);
    c.errors.dy = f64::NAN;
    let err = store.insert_capture(run, &c).unwrap_err();
    assert!(err.to_string().contains("mean of dy is NaN"), "{err}");
    let mut c = capture(1, 0, Direction::Up, 1.0);
    c.u.ez = -1e-9;
    assert!(matches!(
        store.insert_capture(run, &c),
        Err(StoreError::Invalid { .. })
    ));
    let mut c = capture(0, 0, Direction::Up, 1.0);
    c.run = 0;
    assert!(matches!(
        store.insert_capture(run, &c),
        Err(StoreError::Invalid { .. })
    ));
    assert!(store.captures(run).unwrap().is_empty());
}

#[test]
fn captures_cannot_be_updated() {
    let db = TempDb::new("immutable");
    let mut store = Store::open(&db.path).unwrap();
    let run = store.create_run(&new_run()).unwrap();
    store
        .insert_capture(run, &capture(1, 0, Direction::Up, 1.0))
        .unwrap();
    let err = store
        .conn
        .execute("UPDATE captures SET dy_mm = 0", [])
        .unwrap_err();
    assert!(err.to_string().contains("immutable"), "{err}");
}

/// A capture's u stated again leaves the row as taken and is read back as its u in force,
/// the newest of several; a capture not stored (or another one since) takes nothing.
#[test]
fn a_restated_u_is_read_in_force_and_the_capture_kept_as_taken() {
    let db = TempDb::new("restated");
    let mut store = Store::open(&db.path).unwrap();
    let run = store.create_run(&new_run()).unwrap();
    let (c1, c2) = (
        capture(1, 0, Direction::Up, 1.0),
        capture(1, 1, Direction::Up, 2.0),
    );
    store.insert_capture(run, &c1).unwrap();
    store.insert_capture(run, &c2).unwrap();
    let mut r = c2;
    r.u = Errors6::from_array([4e-6, 2e-5, 1e-5, 5e-9, 2e-8, 1e-8]);
    assert!(
        store
            .restate_capture(run, &r, "bounded by a return", 7)
            .unwrap()
    );
    let mut r2 = r;
    r2.u.dx = 3e-6;
    assert!(store.restate_capture(run, &r2, "bounded again", 8).unwrap());
    assert_eq!(store.captures(run).unwrap(), [c1, r2]);
    // The row as taken is there still.
    let u_dx: f64 = store
        .conn
        .query_row(
            "SELECT u_dx_mm FROM captures WHERE run_id = ?1 AND target_index = 1",
            [run.0],
            |row| row.get(0),
        )
        .unwrap();
    assert_eq!(u_dx, c2.u.dx);
    // Another capture of the key (another time), or one not stored: nothing written.
    let mut other = r;
    other.unix_us += 1;
    assert!(
        !store
            .restate_capture(run, &other, "not this one", 9)
            .unwrap()
    );
    let mut absent = capture(2, 0, Direction::Down, 1.0);
    absent.u = r.u;
    assert!(
        !store
            .restate_capture(run, &absent, "not stored", 9)
            .unwrap()
    );
    let why: Vec<String> = store
        .restatements(run)
        .unwrap()
        .into_iter()
        .map(|r| format!("{}: {}", r.key, r.reason))
        .collect();
    assert_eq!(
        why,
        [
            "run 1, target 2: bounded by a return",
            "run 1, target 2: bounded again"
        ]
    );
    let mut bad = r;
    bad.u.dz = f64::NAN;
    assert!(matches!(
        store.restate_capture(run, &bad, "bad", 9),
        Err(StoreError::Invalid { .. })
    ));
}

#[test]
fn handovers_by_run_and_outside_runs() {
    let db = TempDb::new("handovers");
    let mut store = Store::open(&db.path).unwrap();
    let run = store.create_run(&new_run()).unwrap();
    let h1 = handover(20);
    let h2 = HandoverRecord {
        kind: HandoverKind::Encoder,
        ..handover(10)
    };
    let free = handover(5);
    store.insert_handover(Some(run), &h1).unwrap();
    store.insert_handover(Some(run), &h2).unwrap();
    store.insert_handover(None, &free).unwrap();
    let of_run = store.handovers(Some(run)).unwrap();
    assert_eq!(
        of_run.iter().map(|h| h.record).collect::<Vec<_>>(),
        [h2, h1],
        "time order"
    );
    assert!(of_run.iter().all(|h| h.run == Some(run)));
    let outside = store.handovers(None).unwrap();
    assert_eq!(outside.len(), 1);
    assert_eq!(outside[0].record, free);
    assert_eq!(outside[0].run, None);
    assert!(matches!(
        store.insert_handover(Some(RunId(5)), &h1),
        Err(StoreError::NoSuchRun(RunId(5)))
    ));
    let mut bad = h1;
    bad.variance[0] = f64::INFINITY;
    assert!(matches!(
        store.insert_handover(None, &bad),
        Err(StoreError::Invalid { .. })
    ));
}

#[test]
fn calibrations_keep_the_text_and_a_summary() {
    let db = TempDb::new("calibrations");
    let mut store = Store::open(&db.path).unwrap();
    let text_a = calibration_text("aaaa");
    let text_b = calibration_text("bbbb");
    let a = store.insert_calibration(&text_a).unwrap();
    let b = store.insert_calibration(&text_b).unwrap();
    let a2 = store.insert_calibration(&text_a).unwrap();
    let rec = store.calibration(a).unwrap();
    assert_eq!(rec.file_text, text_a);
    assert_eq!(rec.summary.layout_hash, "aaaa");
    assert_eq!(rec.summary.poses, 200);
    assert_eq!(rec.summary.rank, 7);
    assert_eq!(rec.summary.condition_number, 5.6);
    assert_eq!(rec.summary.residual_rms_um, [1.0, 1.1, 1.2, 1.3, 1.4, 1.5]);
    assert_eq!(
        rec.summary.holdout_rms,
        Some([0.5, 1.2, 0.55, 0.3, 1.4, 0.3])
    );
    assert_eq!(rec.summary.file_created, "2025-03-01T10:00:00Z");
    assert_eq!(store.calibrations().unwrap().len(), 3);
    assert_eq!(store.latest_calibration("aaaa").unwrap().unwrap().id, a2);
    assert_eq!(store.latest_calibration("bbbb").unwrap().unwrap().id, b);
    assert!(store.latest_calibration("cccc").unwrap().is_none());
    assert!(matches!(
        store.calibration(CalibrationId(99)),
        Err(StoreError::NoSuchCalibration(_))
    ));
    assert!(matches!(
        store.insert_calibration("not = [a calibration"),
        Err(StoreError::Invalid { .. })
    ));
    // A run can name its calibration.
    let run = store
        .create_run(&NewRun {
            calibration: Some(b),
            ..new_run()
        })
        .unwrap();
    assert_eq!(store.run(run).unwrap().calibration, Some(b));
}

#[test]
fn tables_publications_and_audit() {
    let db = TempDb::new("tables");
    let mut store = Store::open(&db.path).unwrap();
    let run = store.create_run(&new_run()).unwrap();
    let entry = TableEntry {
        kind: "positioning".into(),
        axis: "Y".into(),
        direction: Some(Direction::Down),
        generated_us: 1_700_000_000_000_000,
        source_run: Some(run),
        values: json!({"start_mm": 0.0, "interval_mm": 10.0, "values_um": [0.0, 1.5, -2.25]}),
        crc: 0xCBF4_3926,
    };
    let both = TableEntry {
        direction: None,
        source_run: None,
        crc: 0,
        ..entry.clone()
    };
    let t1 = store.insert_table(&entry).unwrap();
    let t2 = store.insert_table(&both).unwrap();
    assert_eq!(store.table(t1).unwrap().entry, entry);
    assert_eq!(
        store
            .tables()
            .unwrap()
            .into_iter()
            .map(|t| t.entry)
            .collect::<Vec<_>>(),
        [entry.clone(), both]
    );
    assert!(matches!(
        store.table(TableId(9)),
        Err(StoreError::NoSuchTable(_))
    ));
    assert!(matches!(
        store.insert_table(&TableEntry {
            source_run: Some(RunId(50)),
            ..entry.clone()
        }),
        Err(StoreError::NoSuchRun(RunId(50)))
    ));

    let p1 = Publication {
        table: t1,
        target: "cnc-siemens".into(),
        sequence: 7,
        outcome: PublicationOutcome::Failed {
            code: None,
            text: "PLC did not echo the sequence within 5 s".into(),
        },
        unix_us: 1,
    };
    let p2 = Publication {
        sequence: 8,
        outcome: PublicationOutcome::Accepted,
        unix_us: 2,
        ..p1.clone()
    };
    let p3 = Publication {
        table: t2,
        sequence: 9,
        outcome: PublicationOutcome::Rejected {
            code: Some(3),
            text: "CRC mismatch".into(),
        },
        unix_us: 3,
        ..p1.clone()
    };
    for p in [&p1, &p2, &p3] {
        store.insert_publication(p).unwrap();
    }
    let of_t1: Vec<_> = store
        .publications(Some(t1))
        .unwrap()
        .into_iter()
        .map(|p| p.publication)
        .collect();
    assert_eq!(of_t1, [p1.clone(), p2]);
    assert_eq!(store.publications(None).unwrap().len(), 3);
    assert_eq!(store.publications(Some(t2)).unwrap()[0].publication, p3);
    assert!(matches!(
        store.insert_publication(&Publication {
            table: TableId(99),
            ..p1
        }),
        Err(StoreError::NoSuchTable(TableId(99)))
    ));

    let who = Actor {
        uid: Some(1000),
        user: Some("anna".into()),
        pid: Some(4242),
    };
    for (i, action) in ["start-run", "publish", "move-follower"].iter().enumerate() {
        store
            .audit(&AuditEntry {
                unix_us: i as i64,
                who: who.clone(),
                role: "operator".into(),
                action: (*action).into(),
                details: json!({"n": i}),
                outcome: Default::default(),
            })
            .unwrap();
    }
    store
        .audit(&AuditEntry {
            unix_us: 9,
            who: Actor::default(),
            role: "plc".into(),
            action: "acknowledge".into(),
            details: json!(null),
            outcome: Default::default(),
        })
        .unwrap();
    let last = store.audit_entries(2).unwrap();
    assert_eq!(
        last.iter()
            .map(|a| a.entry.action.as_str())
            .collect::<Vec<_>>(),
        ["move-follower", "acknowledge"]
    );
    assert_eq!(last[0].entry.who, who);
    assert_eq!(last[0].entry.details, json!({"n": 2}));
    assert_eq!(last[1].entry.who, Actor::default());
    assert_eq!(store.audit_entries(100).unwrap().len(), 4);
    let err = store.conn.execute("DELETE FROM audit", []).unwrap_err();
    assert!(err.to_string().contains("append-only"), "{err}");
    assert!(matches!(
        store.audit(&AuditEntry {
            unix_us: 0,
            who: Actor::default(),
            role: "operator".into(),
            action: String::new(),
            details: json!({}),
            outcome: Default::default(),
        }),
        Err(StoreError::Invalid { .. })
    ));
}

#[test]
fn a_file_that_is_not_a_database_is_refused_by_name() {
    let db = TempDb::new("garbage");
    std::fs::write(&db.path, vec![0x5a_u8; 8192]).unwrap();
    let err = Store::open(&db.path).unwrap_err();
    assert!(matches!(err, StoreError::NotADatabase { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains(&db.path.display().to_string()), "{msg}");
    assert!(msg.contains("restore a backup"), "{msg}");
    // It was not overwritten.
    assert_eq!(std::fs::read(&db.path).unwrap(), vec![0x5a_u8; 8192]);
}

#[test]
fn a_damaged_database_is_refused_by_name() {
    let db = TempDb::new("damaged");
    {
        let mut store = Store::open(&db.path).unwrap();
        let run = store.create_run(&new_run()).unwrap();
        for t in 0..400 {
            store
                .insert_capture(run, &capture(1, t, Direction::Up, 1.0))
                .unwrap();
        }
    } // closing checkpoints the WAL into the file
    let page: usize = 4096;
    let mut bytes = std::fs::read(&db.path).unwrap();
    assert!(bytes.len() > 8 * page, "enough pages to damage");
    // Scribble over the B-tree pages after the schema page, keep the header.
    let end = bytes.len() - page;
    for b in &mut bytes[2 * page..end] {
        *b = 0xA5;
    }
    std::fs::write(&db.path, &bytes).unwrap();
    let err = Store::open(&db.path).unwrap_err();
    assert!(matches!(err, StoreError::Corrupt { .. }), "{err:?}");
    assert!(
        err.to_string().contains(&db.path.display().to_string()),
        "{err}"
    );
}

#[test]
fn a_future_schema_is_refused_by_name() {
    let db = TempDb::new("future");
    drop(Store::open(&db.path).unwrap());
    {
        let conn = Connection::open(&db.path).unwrap();
        conn.pragma_update(None, "user_version", schema::LATEST + 1)
            .unwrap();
    }
    let err = Store::open(&db.path).unwrap_err();
    assert!(
        matches!(err, StoreError::FutureVersion { found, supported, .. }
            if found == schema::LATEST + 1 && supported == schema::LATEST),
        "{err:?}"
    );
    let msg = err.to_string();
    assert!(msg.contains(&db.path.display().to_string()), "{msg}");
    assert!(msg.contains("newer than this build"), "{msg}");
}

#[test]
fn another_applications_database_is_left_alone() {
    let db = TempDb::new("foreign");
    {
        let conn = Connection::open(&db.path).unwrap();
        conn.execute_batch("CREATE TABLE things (a INTEGER);")
            .unwrap();
    }
    let err = Store::open(&db.path).unwrap_err();
    assert!(matches!(err, StoreError::Foreign { .. }), "{err:?}");
    let conn = Connection::open(&db.path).unwrap();
    let tables: i64 = conn
        .query_row("SELECT count(*) FROM sqlite_schema", [], |r| r.get(0))
        .unwrap();
    assert_eq!(tables, 1, "nothing was added");
}

#[test]
fn read_only_stores_read_but_do_not_write_or_migrate() {
    let db = TempDb::new("readonly");
    assert!(matches!(
        Store::open_read_only(&db.path),
        Err(StoreError::Open { .. })
    ));
    std::fs::write(&db.path, b"").unwrap();
    assert!(matches!(
        Store::open_read_only(&db.path),
        Err(StoreError::NeedsMigration { found: 0, .. })
    ));
    let mut writer = Store::open(&db.path).unwrap();
    let run = writer.create_run(&new_run()).unwrap();
    writer
        .insert_capture(run, &capture(1, 0, Direction::Up, 1.0))
        .unwrap();
    let mut reader = Store::open_read_only(&db.path).unwrap();
    assert!(reader.is_read_only());
    assert_eq!(reader.captures(run).unwrap().len(), 1);
    let err = reader
        .insert_capture(run, &capture(1, 1, Direction::Up, 1.0))
        .unwrap_err();
    assert!(matches!(err, StoreError::ReadOnly { .. }), "{err:?}");
}

#[test]
fn migrations_run_forward_one_transaction_per_step() {
    let db = TempDb::new("migrate");
    let run = {
        let mut store = Store::open(&db.path).unwrap();
        store.create_run(&new_run()).unwrap()
    };
    let mut conn = Connection::open(&db.path).unwrap();
    conn.set_transaction_behavior(TransactionBehavior::Immediate);
    // A failing next step leaves the file at this build's version, without its partial DDL.
    let n = schema::LATEST;
    let mut broken: Vec<&str> = schema::MIGRATIONS.to_vec();
    broken.push("ALTER TABLE runs ADD COLUMN operator TEXT; THIS IS NOT SQL;");
    let (from, to, _) = migrate(&mut conn, &broken).unwrap_err();
    assert_eq!((from, to), (n, n + 1));
    let version: i64 = conn
        .pragma_query_value(None, "user_version", |r| r.get(0))
        .unwrap();
    assert_eq!(version, n);
    assert!(
        conn.prepare("SELECT operator FROM runs").is_err(),
        "the failed step was rolled back"
    );
    // A good next step applies once; the earlier steps are skipped; data is kept.
    let mut steps: Vec<&str> = schema::MIGRATIONS.to_vec();
    steps.push("ALTER TABLE runs ADD COLUMN operator TEXT NOT NULL DEFAULT 'unknown';");
    migrate(&mut conn, &steps).unwrap();
    migrate(&mut conn, &steps).unwrap();
    let (version, operator): (i64, String) = (
        conn.pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap(),
        conn.query_row("SELECT operator FROM runs WHERE id = ?1", [run.0], |r| {
            r.get(0)
        })
        .unwrap(),
    );
    assert_eq!((version, operator.as_str()), (n + 1, "unknown"));
    drop(conn);
    // This build does not know the next version.
    assert!(matches!(
        Store::open(&db.path),
        Err(StoreError::FutureVersion { found, .. }) if found == n + 1
    ));
}

#[test]
fn a_reader_sees_each_commit_while_the_writer_goes_on() {
    let db = TempDb::new("concurrent");
    let run = {
        let mut store = Store::open(&db.path).unwrap();
        store.create_run(&new_run()).unwrap()
    };
    const N: u32 = 150;
    let (tx, rx) = std::sync::mpsc::channel::<u32>();
    let path = db.path.clone();
    let writer = std::thread::spawn(move || {
        let mut store = Store::open(&path).unwrap();
        for t in 0..N {
            assert!(
                store
                    .insert_capture(run, &capture(1, t, Direction::Up, 1.0))
                    .unwrap()
            );
            tx.send(t).unwrap();
        }
    });
    let reader = Store::open_read_only(&db.path).unwrap();
    let mut seen = 0;
    for t in rx {
        // Everything the writer reported committed is visible to the other connection.
        let keys = reader.completed_keys(run).unwrap();
        assert!(keys.len() as u32 > t, "commit {t} not visible");
        assert!(keys.len() >= seen, "a reader never sees fewer rows");
        seen = keys.len();
    }
    writer.join().unwrap();
    assert_eq!(reader.captures(run).unwrap().len(), N as usize);
}

#[test]
fn the_tables_active_during_a_run_are_recorded_once() {
    let db = TempDb::new("run-tables");
    let mut store = Store::open(&db.path).unwrap();
    let before = store.create_run(&new_run()).unwrap();
    let t = store
        .insert_table(&TableEntry {
            kind: "positioning".into(),
            axis: "Y".into(),
            direction: None,
            generated_us: 0,
            source_run: Some(before),
            values: json!({}),
            crc: 0xAA97_89CE,
        })
        .unwrap();
    let run = store.create_run(&new_run()).unwrap();
    assert_eq!(store.run_tables(run).unwrap(), None);
    // Planned and running runs without a record are the tables task's to read.
    assert_eq!(store.runs_without_tables(0).unwrap(), [before, run]);
    let active = RunTables {
        unix_us: 1_700_000_000_000_000,
        known: true,
        source: "generic at 127.0.0.1:1502: sequence 4 read back".into(),
        tables: vec![ActiveTable {
            kind: "positioning".into(),
            axis: "Y".into(),
            table: Some(t),
            sequence: 4,
            crc: 0xAA97_89CE,
            read_back: true,
        }],
    };
    store.record_run_tables(run, &active).unwrap();
    assert_eq!(store.run_tables(run).unwrap().as_ref(), Some(&active));
    assert_eq!(
        active.summary(),
        format!("table {t} (positioning Y, sequence 4)")
    );
    assert_eq!(store.runs_without_tables(0).unwrap(), [before]);
    // Once only; a run or table that does not exist is named.
    let again = store
        .record_run_tables(run, &active)
        .unwrap_err()
        .to_string();
    assert!(again.contains("has them recorded already"), "{again}");
    assert!(matches!(
        store.record_run_tables(RunId(99), &active),
        Err(StoreError::NoSuchRun(RunId(99)))
    ));
    let mut ghost = active.clone();
    ghost.tables[0].table = Some(TableId(77));
    assert!(matches!(
        store.record_run_tables(before, &ghost),
        Err(StoreError::NoSuchTable(TableId(77)))
    ));
    // The failed record left nothing behind.
    assert_eq!(store.run_tables(before).unwrap(), None);
    let unknown = RunTables {
        known: false,
        source: "cannot read the PLC at 127.0.0.1:1502: timed out".into(),
        tables: Vec::new(),
        ..active
    };
    store.record_run_tables(before, &unknown).unwrap();
    assert_eq!(
        store.run_tables(before).unwrap().unwrap().summary(),
        "unknown (cannot read the PLC at 127.0.0.1:1502: timed out)"
    );
}

#[test]
fn the_newest_zero_reference_is_the_one_in_force_across_a_reopen() {
    let db = TempDb::new("references");
    {
        let mut store = Store::open(&db.path).unwrap();
        assert_eq!(
            store.latest_reference().unwrap(),
            None,
            "a new store has none"
        );
        store
            .record_reference(10, "d1", Some(&json!({"errors": [1.5, 0.0]})))
            .unwrap();
        store.record_reference(20, "d1", None).unwrap();
        store
            .record_reference(30, "d2", Some(&json!({"errors": [2.5, -1.0]})))
            .unwrap();
    }
    let store = Store::open(&db.path).unwrap();
    let r = store.latest_reference().unwrap().expect("one recorded");
    assert_eq!((r.unix_us, r.decoupler.as_str()), (30, "d2"));
    let v: serde_json::Value = serde_json::from_str(r.state_json.as_deref().unwrap()).unwrap();
    assert_eq!(v["errors"][0], 2.5);
}

#[test]
fn a_zero_reference_forgotten_is_stored_as_none() {
    let db = TempDb::new("references-none");
    let mut store = Store::open(&db.path).unwrap();
    store
        .record_reference(10, "d1", Some(&json!({"errors": []})))
        .unwrap();
    store.record_reference(11, "d1", None).unwrap();
    let r = store.latest_reference().unwrap().unwrap();
    assert_eq!((r.unix_us, r.state_json), (11, None));
}
