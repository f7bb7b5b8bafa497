//! The record's reader, the plan's order and the fit's wiring; a stored machine on a store on
//! disk, its set-ups refusing runs that cannot stand for them.

use super::fit::{MeasuredSetup, fit};
use super::plan::{self, SETUPS, SetupState};
use super::record::{MachineRecord, parse_chain};
use super::stored::{self, CommissionError};
use crate::comp::mapping::{AxisMapping, MachineAxis};
use crate::machine::squareness::SetupSlopes;
use crate::machine::{Chain, ComponentTable};
use crate::store::{NewRun, RunState, Store};
use crate::units::RAD_PER_ARCSEC;

const RECORD: &str = r#"
name = "VMC 1000 serial 4711"
chain = "workpiece – X – Y – bed – Z – tool"
travel_mm = [1000, 600, 500]
tool_mm = [0, 0, -150]
target_every_mm = 20
runs = 2

[squares.XY]
id = "OS-1"
deviation_arcsec = 0.4
u_arcsec = 0.29
[squares.ZX]
id = "OS-2"
deviation_arcsec = -1.2
u_arcsec = 0.29
[squares.YZ]
id = "OS-3"
deviation_arcsec = 2.0
u_arcsec = 0.29
"#;

fn record() -> MachineRecord {
    MachineRecord::from_toml(RECORD, "machine.toml").expect("the example record")
}

#[test]
fn a_record_reads_with_its_units_and_writes_back_to_the_same_record() {
    let r = record();
    assert_eq!(r.name, "VMC 1000 serial 4711");
    assert_eq!(r.chain, Chain::cross_table());
    assert_eq!(r.travel_mm, [1000.0, 600.0, 500.0]);
    assert_eq!(r.tool_mm, [0.0, 0.0, -150.0]);
    assert_eq!((r.target_every_mm, r.runs), (20.0, 2));
    assert_eq!(r.squares[1].id, "OS-2");
    assert!((r.squares[1].deviation_rad - (-1.2 * RAD_PER_ARCSEC)).abs() < 1e-18);
    assert!((r.squares[2].u_rad - 0.29 * 4.848_136_811_095_36e-6).abs() < 1e-15);
    let again = MachineRecord::from_toml(&r.to_toml(), "written").expect("reads back");
    assert_eq!(again.name, r.name);
    assert_eq!(again.chain, r.chain);
    for (a, b) in again.squares.iter().zip(&r.squares) {
        assert_eq!(a.id, b.id);
        assert!((a.deviation_rad - b.deviation_rad).abs() < 1e-18);
        assert!((a.u_rad - b.u_rad).abs() < 1e-18);
    }
}

#[test]
fn the_example_record_in_configs_reads() {
    let r = MachineRecord::from_toml(
        include_str!("../../configs/machine.toml"),
        "configs/machine.toml",
    )
    .expect("configs/machine.toml");
    assert_eq!(r.chain, Chain::cross_table());
    assert_eq!(r.travel_mm, [1000.0, 600.0, 500.0]);
}

#[test]
fn chains_read_as_written_with_or_without_their_ends() {
    assert_eq!(parse_chain("X Y bed Z"), Ok(Chain::cross_table()));
    assert_eq!(
        parse_chain(&Chain::gantry().to_string()),
        Ok(Chain::gantry())
    );
    assert_eq!(
        parse_chain(&Chain::cross_table().to_string()),
        Ok(Chain::cross_table())
    );
    let e = parse_chain("X Y Z").unwrap_err();
    assert!(e.contains("three axes and one bed"), "{e}");
    let e = parse_chain("X Q bed Z").unwrap_err();
    assert!(e.contains("\"Q\"") && e.contains("not an axis"), "{e}");
    let e = parse_chain("X X bed Z").unwrap_err();
    assert!(e.contains("Y is missing"), "{e}");
}

#[test]
fn a_bad_record_is_refused_with_its_key_and_what_to_do() {
    let cases: [(&str, &str, &str); 6] = [
        (
            "[squares.ZX]\nid = \"OS-2\"\ndeviation_arcsec = -1.2\nu_arcsec = 0.29\n",
            "",
            "squares.ZX: is missing",
        ),
        (
            "travel_mm = [1000, 600, 500]",
            "travel_mm = [1000, 0, 500]",
            "travel_mm: Y is 0 mm",
        ),
        ("runs = 2", "runs = 0", "runs: is 0"),
        (
            "chain = \"workpiece – X – Y – bed – Z – tool\"",
            "chain = \"X Y Z\"",
            "chain: \"X Y Z\"",
        ),
        (
            "u_arcsec = 0.29\n[squares.ZX]",
            "u_arcsec = -1\n[squares.ZX]",
            "squares.XY.u_arcsec",
        ),
        ("runs = 2", "runs = 2\nspeed = 3", "unknown field"),
    ];
    for (from, to, want) in cases {
        let text = RECORD.replacen(from, to, 1);
        assert_ne!(text, RECORD, "the case {want} changed nothing");
        let e = MachineRecord::from_toml(&text, "m.toml")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("machine record m.toml: "), "{e}");
        assert!(e.contains(want), "{e} (wanted {want})");
    }
}

#[test]
fn the_plan_walks_the_set_ups_in_order_and_refuses_one_taken_early() {
    assert_eq!(
        plan::states(&[None; 4]),
        [
            SetupState::Next,
            SetupState::Waiting,
            SetupState::Waiting,
            SetupState::Waiting
        ]
    );
    let two = [Some(7), Some(9), None, None];
    assert_eq!(
        plan::states(&two),
        [
            SetupState::Measured { run_id: 7 },
            SetupState::Measured { run_id: 9 },
            SetupState::Next,
            SetupState::Waiting
        ]
    );
    assert_eq!(plan::refuse_attach(&two, 2), None);
    let e = plan::refuse_attach(&two, 3).expect("refused");
    assert!(e.contains("set-up 3 comes first"), "{e}");
    let e = plan::refuse_attach(&two, 1).expect("refused");
    assert!(e.contains("already measured by run 9"), "{e}");
    assert!(plan::refuse_attach(&two, 4).is_some());
    // Each set-up's run: its axis over its travel, a target every 20 mm.
    let r = record();
    for (i, (axis, _)) in SETUPS.iter().enumerate() {
        let p = plan::run_plan(&r, i);
        assert_eq!(p.axis, axis.to_string());
        assert_eq!((p.start_mm, p.end_mm), (0.0, r.travel_mm[axis.index()]));
        assert_eq!(p.targets, (r.travel_mm[axis.index()] / 20.0) as usize + 1);
        crate::run::Plan::new(p).expect("a valid plan");
    }
    // The steps of a square's set-up name its certificate.
    let steps = plan::steps(&r, 2).join(" ");
    assert!(
        steps.contains("OS-2") && steps.contains("-1.20″"),
        "{steps}"
    );
    assert_eq!(
        plan::title(3),
        "4 of 4: Z through the optical square for YZ"
    );
}

/// A set-up whose axis is straight along its beam but for `slope` (head x, z).
fn setup(axis: MachineAxis, slope: [f64; 2]) -> MeasuredSetup {
    MeasuredSetup {
        table: ComponentTable::new(axis, vec![0.0, 100.0], vec![[0.0; 6]; 2]).expect("table"),
        slopes: SetupSlopes {
            mapping: AxisMapping::standard(axis),
            slope,
            u: [1e-7, 1e-7],
        },
    }
}

#[test]
fn each_squareness_comes_from_its_two_set_ups_and_the_model_from_all_four() {
    let mut r = record();
    for c in &mut r.squares {
        c.deviation_rad = 0.0;
    }
    let axes = SETUPS.map(|(a, _)| a);
    let straight: [Option<MeasuredSetup>; 4] =
        std::array::from_fn(|i| Some(setup(axes[i], [0.0; 2])));
    let f = fit(&r, &straight).expect("fit");
    assert_eq!(f.squareness.len(), 3);
    assert!(f.squareness.iter().all(|s| s.value_rad.abs() < 1e-12));
    assert!(f.model.is_some());
    // Y (set-up 2) leaning in both its slopes moves C0Y (with X) and A0Z (with the second Z
    // set-up), never B0Z (X and the first Z).
    let mut leaning = straight.clone();
    leaning[1] = Some(setup(MachineAxis::Y, [20e-6, 20e-6]));
    let f = fit(&r, &leaning).expect("fit");
    let by_pair: Vec<(String, f64)> = f
        .squareness
        .iter()
        .map(|s| (s.pair.to_string(), s.value_rad))
        .collect();
    assert!(by_pair[0].1.abs() > 10e-6, "{by_pair:?}");
    assert!(by_pair[1].1.abs() < 1e-12, "{by_pair:?}");
    assert!(by_pair[2].1.abs() > 10e-6, "{by_pair:?}");
    // Without the last set-up: C0Y and B0Z, no model.
    let mut three = straight;
    three[3] = None;
    let f = fit(&r, &three).expect("fit");
    let pairs: Vec<String> = f.squareness.iter().map(|s| s.pair.to_string()).collect();
    assert_eq!(pairs, ["XY", "ZX"]);
    assert!(f.model.is_none());
}

/// A store on disk in a fresh directory, removed on drop.
struct TempStore(std::path::PathBuf);

impl TempStore {
    fn new(name: &str) -> (TempStore, Store) {
        let dir =
            std::env::temp_dir().join(format!("axiscomp-commission-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("temp dir");
        let store = Store::open(dir.join("axiscomp.db")).expect("store");
        (TempStore(dir), store)
    }
}

impl Drop for TempStore {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[test]
fn a_stored_machine_takes_only_a_run_that_can_stand_for_its_set_up() {
    let (_dir, mut store) = TempStore::new("attach");
    let id = stored::create(&mut store, RECORD, "machine.toml", 1).expect("created");
    let m = store.machine(id).expect("stored");
    assert_eq!(m.name, "VMC 1000 serial 4711");
    assert_eq!(stored::record(&m).expect("reads back"), record());
    let new_run = |axis: &str| NewRun {
        axis: axis.into(),
        plan: serde_json::json!({}),
        config: serde_json::json!({}),
        calibration: None,
        notes: String::new(),
    };
    let running = store.create_run(&new_run("X")).expect("run");
    store
        .set_run_state(running, RunState::Running)
        .expect("running");
    let y = store.create_run(&new_run("Y")).expect("run");
    store.set_run_state(y, RunState::Running).expect("running");
    store
        .set_run_state(y, RunState::Finished)
        .expect("finished");
    let refused = |setup: usize, run: i64, want: &str, store: &mut Store| {
        let e = stored::attach(store, id, setup, run, 2).unwrap_err();
        assert!(e.to_string().contains(want), "{e} (wanted {want})");
        e
    };
    refused(
        0,
        running.0,
        "is running: attach a finished run",
        &mut store,
    );
    // A Z run started for set-up 4 stands for no other set-up of Z.
    let z = store
        .create_run(&NewRun {
            notes: plan::run_notes(id, 3),
            ..new_run("Z")
        })
        .expect("run");
    store.set_run_state(z, RunState::Running).expect("running");
    store
        .set_run_state(z, RunState::Finished)
        .expect("finished");
    let e = stored::measured_setup(&store, id, &record(), 2, z.0).unwrap_err();
    assert!(
        e.to_string()
            .contains("was measured for set-up 4 of 4: Z through the optical square for YZ"),
        "{e}"
    );
    refused(
        0,
        y.0,
        "measured axis Y: this set-up measures X",
        &mut store,
    );
    let e = refused(1, y.0, "set-up 1 comes first", &mut store);
    assert!(matches!(e, CommissionError::Refused { .. }));
    refused(0, 99, "run 99 is not in the store", &mut store);
    assert!(matches!(
        stored::attach(&mut store, 5, 0, y.0, 2),
        Err(CommissionError::Store(
            crate::store::StoreError::NoSuchMachine(5)
        ))
    ));
    // Nothing was attached; the state says what is next.
    let s = stored::state(&store, id).expect("state");
    assert_eq!(s.attached, [None; 4]);
    assert_eq!(s.states[0], SetupState::Next);
    let e = s.model().unwrap_err();
    assert!(e.contains("4 to go"), "{e}");
    // History: an attachment and a detachment are rows; the newest is in force.
    store
        .set_machine_setup(id, 0, Some(running), 3)
        .expect("attached by hand");
    assert_eq!(store.machine_setups(id, 4).expect("read")[0], Some(running));
    let gone = stored::detach(&mut store, id, 0, 4).expect("detached");
    assert_eq!(gone, [0]);
    assert_eq!(store.machine_setups(id, 4).expect("read"), [None; 4]);
    assert_eq!(store.machines().expect("list").len(), 1);
}

#[test]
fn a_report_of_a_machine_not_measured_yet_is_refused_naming_what_is_missing() {
    let (dir, mut store) = TempStore::new("report");
    let id = stored::create(&mut store, RECORD, "machine.toml", 1).expect("created");
    let out = dir.0.join("report");
    let e = match super::report::write(&store, id, &out, &out.join("controls"), 2) {
        Err(e) => e,
        Ok(_) => panic!("a report without a model"),
    };
    assert!(matches!(e, CommissionError::NoModel(_)), "{e}");
    let text = e.to_string();
    assert!(
        text.contains(&format!("machine {id} is not measured yet: 4 to go"))
            && text.contains("1 of 4: X beam aligned"),
        "{text}"
    );
    // Nothing written: no report of a machine that has none, no control's files.
    assert!(!out.exists());
    let e = super::report::write(&store, id + 1, &out, &out.join("controls"), 2).err();
    assert!(
        matches!(
            e,
            Some(CommissionError::Store(
                crate::store::StoreError::NoSuchMachine(_)
            ))
        ),
        "{e:?}"
    );
}
