//! `axiscomp trend` on a store of an axis's runs (issue 30): limits learned from the first
//! runs, the drift alarm at the run where the reversal the twin would have grown shows, and
//! runs measured under other tables kept out.

use crate::helpers::{TempDir, run, stderr, stdout, store_synthetic_run};
use axiscomp::run::Direction;
use axiscomp::sim::Rng;
use axiscomp::store::{ActiveTable, RunId, RunTables, Store};

/// A finished run of axis X (`helpers::store_synthetic_run`): the down approach
/// `reversal_um` behind the up one, 0.05 µm of scatter per capture; measured under `tables`.
fn store_run(store: &mut Store, rng: &mut Rng, reversal_um: f64, tables: &RunTables) -> RunId {
    store_synthetic_run(store, Some(tables), |_, _, d| {
        (if d == Direction::Down {
            -reversal_um
        } else {
            0.0
        }) + rng.gauss(0.05)
    })
}

#[test]
fn an_axes_reversal_growing_raises_the_drift_alarm_at_the_run_it_shows() {
    let dir = TempDir::new("trend");
    let db = dir.path("axiscomp.db");
    let mut store = Store::open(&db).unwrap();
    let mut rng = Rng::new(30);
    let none = RunTables {
        unix_us: 0,
        known: true,
        source: "generic at 127.0.0.1:1502".into(),
        tables: Vec::new(),
    };
    // Commissioning, uncompensated: not in the trend of the runs under its table.
    store_run(&mut store, &mut rng, 5.0, &none);
    let table = RunTables {
        tables: vec![ActiveTable {
            kind: "positioning".into(),
            axis: "X".into(),
            table: None,
            sequence: 1,
            crc: 0x1234_ABCD,
            read_back: true,
        }],
        ..none.clone()
    };
    // Ten checks under the table with 1.0 µm of reversal left, then it grows by 0.4 µm a run.
    let mut ids = Vec::new();
    for k in 0..14 {
        let grown = 0.4 * (k as f64 - 9.0).max(0.0);
        ids.push(store_run(&mut store, &mut rng, 1.0 + grown, &table));
    }
    drop(store);
    let db = db.to_str().unwrap();
    let o = run(&["trend", "X", "--db", db], "");
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(
        out.contains("axis X: 14 finished runs under the newest's compensation (positioning X sequence 1 CRC 0x1234ABCD)")
            && out.contains("1 earlier run measured under other tables is not in the trend"),
        "{out}"
    );
    // B (the reversal) drifts from the first run it grew in (the 11th of the table's: 1.4 µm
    // against a baseline of 1.0 µm with 0.05 µm of scatter); the positioning shape does not.
    let line = |name: &str| {
        out.lines()
            .find(|l| l.starts_with(name))
            .unwrap_or_else(|| panic!("no line {name}:\n{out}"))
            .to_string()
    };
    let b = line("dy B (reversal)");
    assert!(
        b.contains(&format!("DRIFT since run {}", ids[10])),
        "{b}\n{out}"
    );
    assert!(
        line("dy E (systematic)").contains("DRIFT"),
        "E grows with B: {out}"
    );
    assert!(
        line("dx straightness (least squares)").contains("in control"),
        "{out}"
    );
    // One figure in detail, and as JSON.
    let o = run(&["trend", "X", "dy B", "--db", db], "");
    let detail = stdout(&o);
    eprintln!("{out}\n{detail}");
    assert!(
        detail.contains("dy B (reversal), µm") && detail.contains("← drift alarm"),
        "{detail}"
    );
    let o = run(&["trend", "X", "dy B", "--db", db, "--json"], "");
    let v: serde_json::Value = serde_json::from_str(&stdout(&o)).expect("JSON");
    let f = &v["figures"][0];
    assert_eq!(f["alarm_run"], ids[10].0);
    assert_eq!(f["points"].as_array().map(Vec::len), Some(14));
    let mean = f["mean"].as_f64().unwrap();
    assert!((mean - 1.0).abs() < 0.1, "baseline mean of B {mean} µm");
    // With the configuration's tolerance for B: the runs here were stored within a second, so
    // no date can be forecast from them, and the command says why.
    let cfg = dir.write(
        "axiscomp.toml",
        &format!(
            "[service]\nstate_dir = \"{}\"\n\n[acceptance]\nb_um = 4.0\n",
            dir.path("").display()
        ),
    );
    let o = run(
        &["trend", "X", "dy B", "--config", cfg.to_str().unwrap()],
        "",
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains(
            "forecast: no forecast against its tolerance 4 µm: it needs 3 runs spanning a day or more"
        ),
        "{}",
        stdout(&o)
    );
    // Not a figure of the runs: refused, naming the ones there are.
    let o = run(&["trend", "X", "dy Q", "--db", db], "");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("no figure \"dy q\" in axis X's runs: give one of dx straightness"),
        "{}",
        stderr(&o)
    );
}
