//! Issue 15's maintenance loop on the twin: commission an axis, let it age, re-measure it
//! under the active tables and publish what the re-measurement gives, judged by the twin's
//! truth. The measuring runs are the virtual-time lab's (as `lab::`); the tables go through
//! the service's own tables task (`service::tables::Tables`: generate, publish with its
//! refusals, the PLC read back) over Modbus TCP on loopback into the twin's PLC, which applies
//! them to the lab's axis; every run and table is in an SQLite store on disk.

use axiscomp::comp::{self, AxisMapping, MachineAxis, PositioningMode, TableSpec};
use axiscomp::config::{PlcPush, PlcSettings, Resource, TableBuild};
use axiscomp::evaluate::{EvalOptions, ReferenceLine, evaluate_captures};
use axiscomp::modbus::link::LinkConfig;
use axiscomp::plc::Timeouts;
use axiscomp::plc::table::{self as ptable, PlcTable};
use axiscomp::run::Direction;
use axiscomp::service::api::Request;
use axiscomp::service::stored::StoredTable;
use axiscomp::service::tables::Tables;
use axiscomp::sim::axis::Wear;
use axiscomp::sim::closed_loop::{self, Figures, LoopSpec, Measured, Pass};
use axiscomp::sim::lab::Lab;
use axiscomp::sim::plant::PlantSpec;
use axiscomp::sim::plc::{TwinPlc, TwinPlcConfig};
use axiscomp::store::{NewRun, RunId, RunState, Store, TableEntry};
use std::time::Duration;

const LENGTH_MM: f64 = 200.0;

fn um(mm: f64) -> f64 {
    mm * 1e3
}

/// A 200 mm axis (`lab::square_loop`), 6 targets, 2 runs.
fn loop_spec() -> LoopSpec {
    crate::lab::square_loop(15, LENGTH_MM, 6, 2)
}

/// The lab, the store, the twin's PLC on the lab's plant and the service's tables task.
struct Bench {
    spec: LoopSpec,
    lab: Lab,
    rt: tokio::runtime::Runtime,
    store: Store,
    tables: Tables,
    _plc: TwinPlc,
    _dir: crate::helpers::TempDir,
}

impl Bench {
    fn new() -> Bench {
        let spec = loop_spec();
        let mut lab = Lab::new(&spec.lab).expect("lab");
        closed_loop::prepare(&mut lab, &spec, &mut |_| {}).expect("the lab brought up");
        let dir = crate::helpers::TempDir::new("maintenance");
        let db = dir.path("axiscomp.db");
        let store = Store::open(&db).expect("store");
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("runtime");
        let plc = rt
            .block_on(TwinPlc::start(
                lab.plant.clone(),
                spec.map.clone(),
                TwinPlcConfig::default(),
            ))
            .expect("twin PLC");
        let settings = PlcSettings {
            map: Resource::Builtin("generic".into()),
            push: Some(PlcPush {
                link: LinkConfig::new(plc.local_addr()),
                unit: 0,
            }),
            pull: None,
            timeouts: Timeouts {
                poll: Duration::from_millis(5),
                ..Timeouts::default()
            },
            tables: TableBuild {
                positioning: PositioningMode::Bidirectional,
                straightness: true,
                step_mm: spec.step_mm,
            },
        };
        let tables = rt
            .block_on(Tables::start(spec.map.clone(), &settings, &db))
            .expect("tables task");
        Bench {
            spec,
            lab,
            rt,
            store,
            tables,
            _plc: plc,
            _dir: dir,
        }
    }

    fn ask(&mut self, r: Request) -> Result<serde_json::Value, String> {
        self.rt.block_on(self.tables.request(&r, "maintenance"))
    }

    /// A run as the service makes one: created, the PLC's active tables recorded as it
    /// starts, measured (the lab's cycle), every capture stored, finished.
    fn run(&mut self, pass: Pass, notes: &str) -> (RunId, Measured) {
        let id = self
            .store
            .create_run(&NewRun {
                axis: self.spec.plan.spec.axis.clone(),
                plan: serde_json::to_value(&self.spec.plan).expect("plan"),
                config: serde_json::json!({}),
                calibration: None,
                notes: notes.into(),
            })
            .expect("run");
        self.store
            .set_run_state(id, RunState::Running)
            .expect("running");
        self.rt
            .block_on(self.tables.record_run_tables(id))
            .expect("tables active recorded");
        let m =
            closed_loop::measure(&mut self.lab, &self.spec, pass, &mut |_| {}).expect("measure");
        for c in &m.run.captures {
            self.store.insert_capture(id, &c.capture).expect("capture");
        }
        self.store
            .set_run_state(id, RunState::Finished)
            .expect("finished");
        (id, m)
    }

    /// `table generate` on run `id`: the stored tables' ids and their replies.
    fn generate(&mut self, id: RunId) -> Vec<serde_json::Value> {
        let r = self
            .ask(Request::TableGenerate {
                run_id: id.0,
                residual_only: false,
            })
            .expect("generate");
        r["tables"].as_array().expect("tables").clone()
    }

    fn publish(&mut self, table_id: i64) -> Result<serde_json::Value, String> {
        self.ask(Request::TablePublish {
            table_id,
            confirm: true,
        })
    }

    fn publish_all(&mut self, tables: &[serde_json::Value]) {
        for t in tables {
            let id = t["id"].as_i64().expect("id");
            let r = self.publish(id).expect("publish");
            assert_eq!(r["result"], "committed", "table {id}: {r}");
        }
    }
}

fn truth(m: &Measured) -> Figures {
    m.truth_figures(ReferenceLine::LeastSquares)
        .expect("truth figures")
}

fn show(what: &str, f: &Figures) {
    eprintln!(
        "{what}: truth E {:.2} µm, M {:.2} µm, straightness x {:.2} µm, z {:.2} µm",
        um(f.e),
        um(f.m),
        um(f.straightness_x),
        um(f.straightness_z)
    );
}

/// Commission (measure, publish, verify), age the axis (6 µm of positioning wear
/// mid-travel, 3 µm more backlash, a 5 µm thermal offset at the end of the travel),
/// re-measure under the active tables, generate (composed), publish, verify. By the truth the
/// axis after is within a tenth of the ageing's E and no worse than before re-publishing; the
/// residual alone, and a composed table whose base the PLC no longer holds, are refused.
#[test]
fn re_measuring_an_aged_axis_under_its_tables_and_publishing_the_composed_tables_restores_it() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let mut b = Bench::new();

    // Commissioning: measure, publish, verify.
    let (run1, m1) = b.run(Pass::Before, "commissioning");
    let rt1 = b.store.run_tables(run1).unwrap().expect("recorded");
    assert!(rt1.known && rt1.tables.is_empty(), "{rt1:?}");
    let commissioning = b.generate(run1);
    assert_eq!(
        commissioning.len(),
        3,
        "positioning and both straightnesses"
    );
    for t in &commissioning {
        assert_eq!(t["composition"], "measured", "{t}");
    }
    b.publish_all(&commissioning);
    let (run2, m2) = b.run(Pass::After, "verification");
    let rt2 = b.store.run_tables(run2).unwrap().expect("recorded");
    assert_eq!(rt2.tables.len(), 3, "{rt2:?}");
    assert_eq!(
        rt2.tables.iter().filter(|t| t.read_back).count(),
        1,
        "the last published is read back, the others known from the store: {rt2:?}"
    );
    let (t_before, t_commissioned) = (truth(&m1), truth(&m2));
    show("as built", &t_before);
    show("commissioned", &t_commissioned);
    assert!(t_commissioned.e < 0.1 * t_before.e, "commissioning worked");

    // Years later: the axis aged.
    let wear = Wear {
        positioning_um: 6.0,
        backlash_um: 3.0,
        thermal_um: 5.0,
    };
    b.lab.plant.axis.set_wear(wear);
    let targets = b.spec.plan.targets.clone();
    let ageing: Vec<f64> = targets
        .iter()
        .flat_map(|&x| [Direction::Up, Direction::Down].map(|d| (x, d)))
        .map(|(x, d)| {
            let dir = match d {
                Direction::Up => axiscomp::sim::axis::Direction::Up,
                Direction::Down => axiscomp::sim::axis::Direction::Down,
            };
            b.lab.plant.axis.wear_dy(x, dir)
        })
        .collect();
    let ageing_e = ageing.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        - ageing.iter().cloned().fold(f64::INFINITY, f64::min);
    eprintln!("the ageing's E at the targets: {:.2} µm", um(ageing_e));
    assert!(ageing_e > 8e-3, "the ageing is worth re-measuring");

    // Re-measure under the active tables: the run sees the residual only.
    let (run3, m3) = b.run(Pass::After, "maintenance re-measure");
    let t_aged = truth(&m3);
    show("aged, commissioning tables active", &t_aged);
    let rt3 = b.store.run_tables(run3).unwrap().expect("recorded");
    assert_eq!(rt3.tables.len(), 3, "{rt3:?}");

    // The residual alone, as a table from that run was made before issue 15: refused.
    let residual_id = {
        let eval = evaluate_captures(
            &m3.run
                .captures
                .iter()
                .map(|c| c.capture)
                .collect::<Vec<_>>(),
            &EvalOptions::default(),
        )
        .expect("evaluate");
        let set = comp::build_tables(
            &eval,
            &TableSpec {
                mapping: AxisMapping::standard(MachineAxis::X),
                reference_mm: b.spec.plan.reference_mm,
                positioning: PositioningMode::Bidirectional,
                straightness_line: ReferenceLine::LeastSquares,
                functional_point_mm: None,
            },
        )
        .expect("tables");
        let t = PlcTable::from_comp(&set.positioning, &b.spec.map, b.spec.step_mm).expect("fit");
        let enc = ptable::encode(&t, &b.spec.map, 1).expect("encode");
        let stored = StoredTable::new(&b.spec.map, &t, &set.positioning);
        b.store
            .insert_table(&TableEntry {
                kind: "positioning".into(),
                axis: "X".into(),
                direction: None,
                generated_us: 0,
                source_run: Some(run3),
                values: serde_json::to_value(&stored).expect("json"),
                crc: enc.crc,
            })
            .expect("store the residual")
    };
    let e = b
        .publish(residual_id.0)
        .expect_err("the residual alone is refused");
    eprintln!("refused: {e}");
    assert!(
        e.contains("is the residual alone") && e.contains(&format!("run {run3}")),
        "{e}"
    );

    // Generate from the re-measurement: the active tables plus the residual, on their grids.
    let composed = b.generate(run3);
    assert_eq!(composed.len(), 3);
    for (c, old) in composed.iter().zip(&commissioning) {
        let comp_text = c["composition"].as_str().unwrap_or_default();
        assert!(
            comp_text.starts_with(&format!("composed: table {} (sequence", old["id"]))
                && comp_text.contains(&format!("residual measured by run {run3}")),
            "{c}"
        );
        for k in ["start_mm", "interval_mm", "points"] {
            assert_eq!(c[k], old[k], "{k}: the active table's grid");
        }
    }
    // The composed positioning table holds the ageing: at mid-travel it grew by about the
    // wear there (6 µm of wear, 2.5 µm of thermal offset; ±1.5 µm backlash per direction).
    let mid = |t: &serde_json::Value| {
        let v = t["values_um"].as_array().expect("values");
        let i = v.len() / 2;
        v[i].as_f64().unwrap_or(f64::NAN)
    };
    let grew = mid(&composed[0]) - mid(&commissioning[0]);
    eprintln!("positioning at mid-travel grew by {grew:.2} µm (+ direction)");
    let want = um(b
        .lab
        .plant
        .axis
        .wear_dy(LENGTH_MM / 2.0, axiscomp::sim::axis::Direction::Up)
        - b.lab
            .plant
            .axis
            .wear_dy(b.spec.plan.reference_mm, axiscomp::sim::axis::Direction::Up));
    assert!(
        (grew - want).abs() < 1.0,
        "grew {grew:.2} µm, wear {want:.2} µm"
    );

    // `axiscomp export --run N` on the store (no service) composes the same way and says so.
    let db = b.store.path().display().to_string();
    let export = |run: RunId, file: &str| {
        let out = b._dir.path(file);
        let o = crate::helpers::run(
            &[
                "export",
                "--db",
                &db,
                "--run",
                &run.0.to_string(),
                "--format",
                "csv",
                "--bidirectional",
                "--out",
                &out.display().to_string(),
            ],
            "",
        );
        assert!(o.status.success(), "{}", crate::helpers::stderr(&o));
        (
            std::fs::read_to_string(&out).expect("exported"),
            crate::helpers::stderr(&o),
        )
    };
    let (csv, said) = export(run3, "aged.csv");
    let line = format!("composed: table {} (sequence", commissioning[0]["id"]);
    assert!(
        csv.lines()
            .take(3)
            .any(|l| l.starts_with(&format!("# {line}")))
            && said.contains(&line),
        "{said}\n{csv}"
    );
    let (csv, said) = export(run1, "commissioning.csv");
    assert!(
        !csv.contains("composed") && !said.contains("composed"),
        "{csv}"
    );

    b.publish_all(&composed);
    let (_run4, m4) = b.run(Pass::After, "maintenance verification");
    let t_after = truth(&m4);
    show("re-published", &t_after);
    eprintln!(
        "E: {:.2} µm aged → {:.2} µm re-published ({:.1} % of the ageing's E {:.2} µm)",
        um(t_aged.e),
        um(t_after.e),
        100.0 * t_after.e / ageing_e,
        um(ageing_e)
    );
    assert!(
        t_after.e <= 0.1 * ageing_e,
        "E after {:.2} µm, the ageing's E {:.2} µm",
        um(t_after.e),
        um(ageing_e)
    );
    for (name, before, after) in [
        ("E", t_aged.e, t_after.e),
        ("M", t_aged.m, t_after.m),
        (
            "straightness x",
            t_aged.straightness_x,
            t_after.straightness_x,
        ),
        (
            "straightness z",
            t_aged.straightness_z,
            t_after.straightness_z,
        ),
    ] {
        assert!(
            after <= before + 0.2e-3,
            "{name}: {:.2} µm before re-publishing, {:.2} µm after",
            um(before),
            um(after)
        );
    }

    // The commissioning run's tables again, composed on what the PLC held then: refused now.
    let stale = b.generate(run3);
    let e = b
        .publish(stale[0]["id"].as_i64().expect("id"))
        .expect_err("a base the PLC no longer holds is refused");
    eprintln!("refused: {e}");
    assert!(e.contains("its base is not what the PLC holds"), "{e}");

    // Found later: `run list` on the store alone, and the audit log naming its objects.
    let o = crate::helpers::run(&["run", "list", "--db", &db, "--json"], "");
    assert!(o.status.success(), "{}", crate::helpers::stderr(&o));
    let runs: serde_json::Value =
        serde_json::from_str(&crate::helpers::stdout(&o)).expect("run list JSON");
    let runs = runs.as_array().expect("runs");
    assert_eq!(runs.len(), 4);
    let r3 = &runs[2];
    assert_eq!(r3["notes"], "maintenance re-measure");
    assert_eq!(
        (r3["start_mm"].as_f64(), r3["end_mm"].as_f64()),
        (Some(0.0), Some(LENGTH_MM))
    );
    assert_eq!(r3["plan"], "6 targets, 2 runs, 2 s dwell, 3000 mm/min");
    assert_eq!(r3["state"], "finished");
    let date = r3["date"].as_str().unwrap_or_default();
    assert!(
        date.len() == 20 && date.as_bytes()[10] == b'T' && date.ends_with('Z'),
        "{date}"
    );
    let active = r3["tables_active"].as_str().unwrap_or_default();
    assert!(
        active.contains(&format!(
            "table {} (positioning X, sequence 1)",
            commissioning[0]["id"]
        )),
        "{active}"
    );
    assert_eq!(runs[0]["tables_active"], "none");
    let o = crate::helpers::run(&["run", "list", "--db", &db], "");
    let text = crate::helpers::stdout(&o);
    assert!(text.contains(&format!("run 3    {date}")), "{text}");
    let audit = b.store.audit_entries(100).expect("audit");
    let published: Vec<_> = audit
        .iter()
        .filter(|a| a.entry.action == "table_published")
        .collect();
    assert!(
        published.iter().any(|a| a.entry.details["sequence"] == 4
            && a.entry.details["table_id"] == composed[0]["id"]
            && a.entry.details["result"] == "committed"),
        "{published:?}"
    );
}

/// The twin's control socket ages the axis while it runs (`{"cmd":"age",…}`): the wear given
/// is in force at once (the positioning error the plant adds mid-travel against the `Wear`
/// formula worked by hand), and a bad value is refused naming its field, the wear unchanged.
#[tokio::test]
async fn the_twin_ages_its_axis_through_its_control_socket() {
    use axiscomp::sim::axis::Direction as Moving;
    use axiscomp::sim::twin::{Twin, TwinCan, TwinSpec};
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let twin = Twin::start(
        &axiscomp::optics::Layout::reference(),
        TwinSpec {
            plant: PlantSpec::default(),
            io_bind: "127.0.0.1:0".parse().expect("addr"),
            io_map: axiscomp::acquire::IoMap::generic().expect("generic map"),
            can: TwinCan::Memory(axiscomp::can::memory::MemoryBus::new(64)),
            drive: Default::default(),
            control: Some("127.0.0.1:0".parse().expect("addr")),
        },
    )
    .await
    .expect("twin");
    let addr = twin.control_addr().expect("a control socket");
    let s = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let (rd, mut wr) = s.into_split();
    let mut lines = BufReader::new(rd).lines();
    let mut ask = async |req: &str| -> serde_json::Value {
        wr.write_all(format!("{req}\n").as_bytes())
            .await
            .expect("send");
        let line = lines.next_line().await.expect("read").expect("a reply");
        serde_json::from_str(&line).expect("JSON reply")
    };
    let axis = &twin.plant.axis;
    assert_eq!(axis.wear(), Wear::default());
    let r = ask(r#"{"cmd":"age","positioning_um":6,"backlash_um":3,"thermal_um":5}"#).await;
    assert_eq!(r["ok"], true, "{r}");
    assert_eq!(r["wear"]["backlash_um"], 3.0);
    // Mid-travel of 1000 mm: 6·sin²(π/2) + 5·0.5 ∓ 3/2 = 7.0 µm up, 10.0 µm down.
    assert!((axis.wear_dy(500.0, Moving::Up) * 1e3 - 7.0).abs() < 1e-9);
    assert!((axis.wear_dy(500.0, Moving::Down) * 1e3 - 10.0).abs() < 1e-9);
    // At 0 only the backlash's half.
    assert!((axis.wear_dy(0.0, Moving::Up) * 1e3 + 1.5).abs() < 1e-9);
    let r = ask(r#"{"cmd":"age","backlash_um":-2}"#).await;
    assert_eq!(r["ok"], false);
    assert_eq!(r["error"], "age \"backlash_um\" is -2 µm: give 0 to 100 µm");
    let r = ask(r#"{"cmd":"age","thermal_um":1e3}"#).await;
    assert_eq!(
        r["error"],
        "age \"thermal_um\" is 1000 µm: give 0 to 100 µm"
    );
    assert_eq!(axis.wear().backlash_um, 3.0);
    assert_eq!(axis.wear().thermal_um, 5.0);
    // Only the field given changes; the bare command reports the wear in force.
    ask(r#"{"cmd":"age","thermal_um":0}"#).await;
    let r = ask(r#"{"cmd":"age"}"#).await;
    assert_eq!(
        r["wear"],
        serde_json::json!({"positioning_um": 6.0, "backlash_um": 3.0, "thermal_um": 0.0})
    );
}
