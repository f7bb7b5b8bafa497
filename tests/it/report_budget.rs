//! Issue 14: a stored run's uncertainty budget (ISO/TR 230-9) in `axiscomp report`, from what
//! the run recorded when it started — the follower map it used (read back by id), the
//! calibration's term, the drift check, the temperature inputs, PSD2's sensitivities — checked
//! value by value against an independent root-sum-square of those inputs; a run stored
//! before runs recorded them still reports, naming the terms "not recorded".

use crate::helpers::{TempDir, bin, stderr, stdout};
use axiscomp::evaluate::axis::synthetic_capture;
use axiscomp::evaluate::recorded::{
    KEY, RecordedBudget, RecordedCalibration, RecordedDrift, RecordedMap, RecordedThermal, Stated,
};
use axiscomp::evaluate::uncertainty::Component;
use axiscomp::follower::{self, Certificate, MapSettings};
use axiscomp::run::{Direction, Plan, PlanSpec};
use axiscomp::store::{NewRun, RunId, RunState, Store};
use axiscomp::track::{HandoverKind, HandoverRecord};
use axiscomp::units::{DOF_NAMES, DOF_TO_USER, Errors6};
use std::path::PathBuf;

/// The follower's certificate: standard uncertainty 0.2 µm up to 100 mm, rising to 0.6 µm at
/// 500 mm (one direction applies to both).
const CERT: &str = "position_mm,error_um,direction,uncertainty_um\n\
    0,0.0,+,0.2\n100,0.5,+,0.2\n200,0.8,+,0.3\n300,1.0,+,0.4\n400,0.9,+,0.5\n500,0.7,+,0.6\n";

/// Certificate u (µm) at encoder position x, linear between its points, held beyond them.
fn cert_u(x: f64) -> f64 {
    let x = x.clamp(0.0, 500.0);
    let p = [0.0, 100.0, 200.0, 300.0, 400.0, 500.0];
    let u = [0.2, 0.2, 0.3, 0.4, 0.5, 0.6];
    let i = p.iter().rposition(|&q| q <= x).expect("inside").min(4);
    u[i] + (u[i + 1] - u[i]) * (x - p[i]) / (p[i + 1] - p[i])
}

/// The encoder read this much more than the carriage when the run started (mm).
const ENCODER_OFFSET_MM: f64 = 2.5;
/// Recorded: the calibration's u (µm, arcsec), the drift check's range (µm, arcsec), PSD2's
/// sensitivities (internal units per mm of X2 and of Y2), temperature inputs.
const CAL_U: [f64; 6] = [0.30, 0.50, 0.20, 0.05, 0.40, 0.06];
const DRIFT: [f64; 6] = [1.2, 2.0, 0.8, 0.3, 0.6, 0.2];
const SENS: [[f64; 2]; 6] = [
    [0.5, 0.0],
    [1.0, 0.0],
    [0.0, 0.02],
    [0.0, 0.0],
    [0.0, 1.0 / 150.0],
    [1e-4, 0.0],
];
const ALPHA: f64 = 11.5;
const U_ALPHA: f64 = 0.58;
const U_T: f64 = 0.1;
const MATERIAL_C: f64 = 20.2;
/// An overlap handover before the run's captures, its variance (mm², along and vertical).
const STITCH_VAR: [f64; 2] = [0.04e-6, 0.09e-6];

const RUNS: u32 = 3;
/// Run-to-run offsets of every DOF (user units) and the frame scatter of every capture.
const OFFSETS: [f64; 3] = [-0.3, 0.1, 0.2];
const FRAME_SD: f64 = 0.5;
const FRAMES: u32 = 200;

fn plan() -> Plan {
    Plan::new(PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm: 400.0,
        targets: 5,
        runs: RUNS,
        overrun_mm: 5.0,
        dwell_s: 2.0,
        feed_mm_min: 2000.0,
        lead_mm: 0.0,
        reference_mm: None,
    })
    .expect("plan")
}

/// The value of DOF `k` (user units) at target `t`, run `r`, direction `d`: the run offsets
/// scaled per DOF and direction (so every cell has its own s), a reversal in dy, a 20 µm/m
/// line in dz (the beam's slope).
fn value(k: usize, t: usize, x: f64, r: usize, d: Direction) -> f64 {
    let up = d == Direction::Up;
    let scale = (1.0 + 0.3 * k as f64) * if up { 1.0 } else { 1.5 } * (1.0 + 0.1 * t as f64);
    let base = match k {
        1 if up => 1.0,
        1 => -1.0,
        2 => 20.0 * x / 1000.0,
        _ => 0.0,
    };
    base + scale * OFFSETS[r]
}

/// A store with run 1 (`config` as its configuration) over `plan()`, captures of known
/// scatter, an overlap handover before them; and `maps` follower maps from the certificate,
/// the last in use; the run's calibration `calibration` (a file's text), stored. Returns the
/// store's path and the maps' ids.
fn store(
    dir: &TempDir,
    config: impl FnOnce(&[i64]) -> serde_json::Value,
    maps: usize,
    calibration: Option<&str>,
) -> (PathBuf, Vec<i64>) {
    let path = dir.path("axiscomp.db");
    let mut s = Store::open(&path).expect("store");
    let cert = Certificate::parse(CERT, "stage.csv").expect("certificate");
    let map = follower::build(&[], Some(&cert), &MapSettings::default()).expect("map");
    let ids: Vec<i64> = (0..maps)
        .map(|i| {
            s.insert_follower_map(&map, &format!("stage-{}.csv", i + 1), true)
                .expect("map")
        })
        .collect();
    let calibration = calibration.map(|text| s.insert_calibration(text).expect("calibration"));
    let plan = plan();
    let id = s
        .create_run(&NewRun {
            axis: "X".into(),
            plan: serde_json::to_value(&plan).expect("plan json"),
            config: config(&ids),
            calibration,
            notes: "budget".into(),
        })
        .expect("run");
    s.insert_handover(
        Some(id),
        &HandoverRecord {
            unix_us: 1_000,
            kind: HandoverKind::Overlap,
            before: [0.0; 2],
            after: [0.0; 2],
            n_before: 100,
            n_after: 100,
            frame_sd: [1e-3; 2],
            encoder_before: 0.0,
            encoder_after: 3.0,
            delta: [3.0, 0.0],
            variance: STITCH_VAR,
        },
    )
    .expect("handover");
    let mut at = 2_000;
    for (t, &x) in plan.targets.iter().enumerate() {
        for r in 0..RUNS as usize {
            for d in [Direction::Up, Direction::Down] {
                let e: [f64; 6] = std::array::from_fn(|k| value(k, t, x, r, d));
                let mut c = synthetic_capture(
                    t as u32,
                    x,
                    r as u32 + 1,
                    d,
                    Errors6::from_user(e),
                    Errors6::from_user([0.05; 6]),
                );
                c.frame_sd = Errors6::from_user([FRAME_SD; 6]);
                c.frames = FRAMES;
                c.material_c = Some(MATERIAL_C);
                c.unix_us = at;
                at += 1_000;
                s.insert_capture(id, &c).expect("capture");
            }
        }
    }
    s.set_run_state(id, RunState::Running).expect("state");
    s.set_run_state(id, RunState::Finished).expect("state");
    (path, ids)
}

fn recorded(map_id: i64) -> RecordedBudget {
    RecordedBudget {
        follower_map: Stated::Stated(RecordedMap {
            id: map_id,
            name: "stage-1.csv".into(),
            source: "certificate".into(),
            created: "2026-02-01T08:00:00Z".into(),
            encoder_offset_mm: Some(ENCODER_OFFSET_MM),
        }),
        follower_spec_um: None,
        calibration: Stated::Stated(RecordedCalibration {
            id: None,
            u_um_arcsec: CAL_U,
            source: "the bench's hold-out".into(),
        }),
        drift: Stated::Stated(RecordedDrift {
            range_um_arcsec: DRIFT,
            duration_s: Some(600.0),
        }),
        thermal: Stated::Stated(RecordedThermal {
            alpha_um_per_m_k: ALPHA,
            u_alpha_um_per_m_k: U_ALPHA,
            u_temperature_k: U_T,
        }),
        psd2_sensitivity: Some(SENS),
    }
}

/// `axiscomp report --run 1 --json` on `db`, with `extra` arguments.
fn report_json(db: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "report",
        "--db",
        db.to_str().expect("path"),
        "--run",
        "1",
        "--json",
    ];
    args.extend_from_slice(extra);
    let o = bin().args(&args).output().expect("run axiscomp");
    assert!(o.status.success(), "{}{}", stdout(&o), stderr(&o));
    serde_json::from_str(&stdout(&o)).expect("json")
}

/// Mean and sample standard deviation.
fn mean_sd(x: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    let m = x.iter().sum::<f64>() / n;
    (
        m,
        (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(),
    )
}

/// Every term of one DOF at one target and direction (`None`: the mean), user units, by hand
/// from the recorded inputs (ISO/TR 230-9: each contributor's standard uncertainty).
fn expected(k: usize, t: usize, x: f64, dir: Option<Direction>) -> Vec<(&'static str, f64)> {
    let user = DOF_TO_USER[k];
    let n = RUNS as f64;
    let cell = |d: Direction| {
        let v: Vec<f64> = (0..RUNS as usize).map(|r| value(k, t, x, r, d)).collect();
        let s = mean_sd(&v).1;
        // Frame scatter over FRAMES frames, n captures, mean of n.
        let noise = (n * FRAME_SD * FRAME_SD / FRAMES as f64).sqrt() / n;
        (noise, s)
    };
    let (noise, repeat) = match dir {
        Some(d) => {
            let (noise, s) = cell(d);
            (noise, s / n.sqrt())
        }
        None => {
            let (nu, su) = cell(Direction::Up);
            let (nd, sd) = cell(Direction::Down);
            (
                (nu * nu + nd * nd).sqrt() / 2.0,
                (su * su / n + sd * sd / n).sqrt() / 2.0,
            )
        }
    };
    // Follower: the map's u at the point and at the zero reference (0 mm), encoder = carriage
    // + offset, through PSD2's sensitivities (mm → the DOF's internal unit → user).
    let along_mm = cert_u(x + ENCODER_OFFSET_MM).hypot(cert_u(ENCODER_OFFSET_MM)) * 1e-3;
    let follower = SENS[k][0] * along_mm * user;
    let stitching =
        (SENS[k][0].powi(2) * STITCH_VAR[0] + SENS[k][1].powi(2) * STITCH_VAR[1]).sqrt() * user;
    let l = x; // from the zero reference at 0 mm
    // The beam's angle to the travel from the straightness slopes: dz rises 20 µm/m.
    let phi = 20e-6f64.atan();
    let (misalignment, t_temp, t_coef) = if k == 1 {
        (
            // 1 − cos φ as 2·sin²(φ/2): at 20 µrad the difference cancels to 1e-7.
            l * 2.0 * (phi / 2.0).sin().powi(2) / 12f64.sqrt() * 1e3,
            ALPHA * U_T * l * 1e-3,
            U_ALPHA * (MATERIAL_C - 20.0) * l * 1e-3,
        )
    } else {
        (0.0, 0.0, 0.0)
    };
    vec![
        ("PSD noise", noise),
        ("repeatability", repeat),
        ("calibration", CAL_U[k]),
        ("follower map", follower),
        ("stitching", stitching),
        ("misalignment", misalignment),
        ("thermal, temperature", t_temp),
        ("thermal, coefficient", t_coef),
        ("environmental variation", DRIFT[k] / (2.0 * 3f64.sqrt())),
    ]
}

fn close(got: f64, want: f64, what: &str) {
    assert!(
        (got - want).abs() <= 1e-9 * want.abs().max(1e-6),
        "{what}: report {got:e}, by hand {want:e}"
    );
}

/// A stored run with a follower map and a calibration term recorded: the report's budget,
/// every term and U at every point of every DOF, equals the root-sum-square of the recorded
/// inputs computed here; each term's source names where it came from; `--json` carries the
/// record; the instrument section names the run's map and that another map is in use now.
#[test]
fn the_report_states_the_budget_the_run_recorded() {
    let dir = TempDir::new("report-budget");
    let (db, maps) = store(
        &dir,
        |ids| serde_json::json!({"dialect": "iso", KEY: recorded(ids[0]).to_json()}),
        2,
        None,
    );
    let j = report_json(&db, &[]);
    let b = &j["budget"];
    assert_eq!(b["k"], 2.0);
    let plan = plan();
    let mut checked = 0;
    for (k, d) in b["dofs"].as_array().expect("dofs").iter().enumerate() {
        assert_eq!(d["dof"], DOF_NAMES[k]);
        for p in d["points"].as_array().expect("points") {
            let x = p["target_mm"].as_f64().expect("target");
            let t = plan
                .targets
                .iter()
                .position(|&q| (q - x).abs() < 1e-9)
                .expect("a target");
            let dir = match p["direction"].as_str().expect("direction") {
                "+" => Some(Direction::Up),
                "-" => Some(Direction::Down),
                _ => None,
            };
            let terms = expected(k, t, x, dir);
            let what = |name: &str| format!("{} at {x} mm {:?}: {name}", DOF_NAMES[k], dir);
            for (name, want) in &terms {
                let got = p["terms"][name]
                    .as_f64()
                    .unwrap_or_else(|| panic!("{name}"));
                close(got, *want, &what(name));
            }
            let u = terms.iter().map(|(_, v)| v * v).sum::<f64>().sqrt();
            close(p["u"].as_f64().expect("u"), u, &what("u"));
            close(p["U"].as_f64().expect("U"), 2.0 * u, &what("U"));
            checked += 1;
        }
        // Every term is stated, and says where it came from.
        let sources: Vec<&str> = d["terms"]
            .as_array()
            .expect("terms")
            .iter()
            .map(|t| t["source"].as_str().expect("source"))
            .collect();
        assert!(
            sources
                .iter()
                .all(|s| !s.contains("not stated") && !s.contains("not recorded")),
            "{sources:?}"
        );
        assert!(
            sources[2].contains("recorded with the run: the bench's hold-out"),
            "{}",
            sources[2]
        );
        assert!(
            sources[3].contains(&format!(
                "follower error map: id {} \"stage-1.csv\"",
                maps[0]
            )) && sources[3].contains("encoder read 2.500 mm more than the carriage"),
            "{}",
            sources[3]
        );
        assert!(
            sources[Component::Environment.index()].contains("drift check")
                && sources[Component::Environment.index()].contains("600 s"),
            "{}",
            sources[Component::Environment.index()]
        );
        assert!(
            sources[Component::ThermalTemperature.index()].contains("11.50")
                && sources[Component::ThermalTemperature.index()].contains("+0.20 K"),
            "{}",
            sources[Component::ThermalTemperature.index()]
        );
    }
    assert_eq!(
        checked,
        6 * 5 * 3,
        "every DOF, target and direction and the mean"
    );
    // The record itself, as the run stored it.
    assert_eq!(j["budget_inputs"]["follower_map"]["stated"]["id"], maps[0]);
    assert_eq!(
        j["budget_inputs"]["calibration"]["stated"]["u_um_arcsec"][4],
        0.4
    );

    // The acceptance report: the map the run used, and that it differs from the one in use.
    let out = dir.path("acc");
    let o = bin()
        .args([
            "report",
            "--db",
            db.to_str().expect("p"),
            "--run",
            "1",
            "--format",
            "md",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("report");
    assert!(o.status.success(), "{}", stderr(&o));
    let md = std::fs::read_to_string(out.join("acceptance.md")).expect("md");
    let line = |label: &str| {
        md.lines()
            .find(|l| l.starts_with(&format!("| **{label}**")))
            .unwrap_or_else(|| panic!("{label} in\n{md}"))
            .to_string()
    };
    let map = line("Follower map");
    assert!(
        map.contains(&format!("id {} \"stage-1.csv\" (certificate), made 2026-02-01 08:00:00 UTC; in use when the run started", maps[0]))
            && map.contains(&format!("the map in use now differs: id {} \"stage-2.csv\"", maps[1])),
        "{map}"
    );
    assert!(line("Budget inputs").contains("recorded with the run"));
    // The budget table: dy's calibration and drift terms as recorded, k = 2 stated.
    assert!(md.contains("Budget per ISO/TR 230-9 (k = 2)"), "{md}");
    let row = md
        .lines()
        .find(|l| l.starts_with("| calibration |"))
        .expect("calibration row");
    assert_eq!(
        row,
        "| calibration | 0.300 | 0.500 | 0.200 | 0.050 | 0.400 | 0.060 |"
    );
    let row = md
        .lines()
        .find(|l| l.starts_with("| environmental variation | "))
        .expect("drift row");
    assert!(
        row.starts_with("| environmental variation | 0.346 | 0.577 |"),
        "{row}"
    );
}

/// A run stored before runs recorded their budget's inputs: it still reports; the follower,
/// calibration, temperature and drift terms are not in u and are named "not recorded" in
/// the JSON and in the acceptance report; `--follower-spec-um` stands in for the map.
#[test]
fn an_old_run_reports_its_terms_as_not_recorded() {
    let dir = TempDir::new("report-budget-old");
    let (db, _) = store(
        &dir,
        |_| serde_json::json!({"capture": {"stable_window_s": 0.5}, "dialect": "iso"}),
        1,
        None,
    );
    let j = report_json(&db, &[]);
    assert!(
        j["budget_inputs"]["not_recorded"]
            .as_str()
            .is_some_and(|s| s.starts_with("not recorded")),
        "{}",
        j["budget_inputs"]
    );
    for d in j["budget"]["dofs"].as_array().expect("dofs") {
        for t in d["terms"].as_array().expect("terms") {
            let name = t["name"].as_str().expect("name");
            let source = t["source"].as_str().expect("source");
            let unrecorded = matches!(
                name,
                "calibration"
                    | "follower map"
                    | "follower map, this set-up's bend"
                    | "thermal, temperature"
                    | "thermal, coefficient"
                    | "environmental variation"
            );
            assert_eq!(
                source.starts_with("not recorded"),
                unrecorded,
                "{name}: {source}"
            );
            if unrecorded {
                assert_eq!(t["largest_u"], 0.0, "{name}");
            }
        }
        // u is noise, repeatability, stitching and misalignment alone.
        for p in d["points"].as_array().expect("points") {
            let terms = &p["terms"];
            let u = ["PSD noise", "repeatability", "stitching", "misalignment"]
                .iter()
                .map(|n| terms[n].as_f64().expect("term").powi(2))
                .sum::<f64>()
                .sqrt();
            close(
                p["u"].as_f64().expect("u"),
                u,
                "u without the unrecorded terms",
            );
        }
    }
    // The follower's specification stands in for the unrecorded map: ±4 µm → 4/√3 µm of dy.
    let j = report_json(&db, &["--follower-spec-um", "4,2"]);
    let dy = &j["budget"]["dofs"][1];
    let f = dy["terms"][3]["largest_u"].as_f64().expect("follower");
    assert!(f > 0.0, "the specification is used: {f}");
    assert!(
        dy["terms"][3]["source"]
            .as_str()
            .is_some_and(|s| s.contains("specification, ±4.0 µm")),
        "{}",
        dy["terms"][3]
    );

    let out = dir.path("acc");
    let o = bin()
        .args([
            "report",
            "--db",
            db.to_str().expect("p"),
            "--run",
            "1",
            "--format",
            "md",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("report");
    assert!(o.status.success(), "{}", stderr(&o));
    let md = std::fs::read_to_string(out.join("acceptance.md")).expect("md");
    assert!(
        md.lines()
            .any(|l| l.starts_with("| **Follower map** | not recorded with the run")),
        "{md}"
    );
    assert!(
        md.contains("| **Budget inputs** | not recorded: the run was stored before"),
        "{md}"
    );
    assert!(
        md.contains("| calibration | – | – | – | – | – | – |"),
        "{md}"
    );
    assert!(
        md.lines()
            .any(|l| l.starts_with("| **calibration** | √(") && l.contains("— not recorded")),
        "{md}"
    );
}

/// A calibration file with a diagonal β (µm per µm / arcsec) and a hold-out: the bound of one
/// reading is σ_k/β_kk = (0.5, 2, 0.5, 0.25, 4, 0.25) by hand.
fn calibration_text() -> String {
    use axiscomp::calibrate::file::{CalibrationFile, FORMAT, LinearSection, Meta};
    let diag = [2.0, 1.0, 2.0, 4.0, 0.5, 4.0];
    CalibrationFile {
        meta: Meta {
            format: FORMAT,
            created: "2026-03-01T10:00:00Z".into(),
            layout: "reference".into(),
            layout_hash: "0".into(),
            poses: 250,
            fit_poses: 200,
            holdout_poses: 50,
            travel_mm: [0.0, 0.0],
            noise_um: [1.0, 2.0, 1.0, 1.0, 2.0, 1.0],
        },
        linear: LinearSection {
            rank: 6,
            rcond: 1e-12,
            condition_number: 8.0,
            ref_travel_mm: 0.0,
            ref_follower_mm: 0.0,
            residual_rms_um: [1.0; 6],
            holdout_rms: Some([0.6, 1.0, 0.5, 0.5, 5.0, 0.2]),
            singular_values: diag.to_vec(),
            offset_um: [0.0; 6],
            beta: std::array::from_fn(|r| {
                std::array::from_fn(|k| if r == k { diag[k] } else { 0.0 })
            }),
        },
        model: None,
    }
    .to_toml()
}

/// A run stored before runs recorded their budget's inputs, but with its calibration in the
/// store: the calibration term follows from the stored file, u² = max(0, h² − b²) + √(2/N)·b²
/// with N = 50 hold-out poses (√(2/N) = 0.2): 0.16, 0.8, 0.05, 0.2, 12.2, 0.0125 (µm², ″²).
#[test]
fn an_old_run_with_a_stored_calibration_states_its_term_from_the_file() {
    let dir = TempDir::new("report-budget-old-cal");
    let text = calibration_text();
    let (db, _) = store(&dir, |_| serde_json::json!({}), 1, Some(&text));
    let j = report_json(&db, &[]);
    let want = [0.16f64, 0.8, 0.05, 0.2, 12.2, 0.0125].map(f64::sqrt);
    for (k, d) in j["budget"]["dofs"]
        .as_array()
        .expect("dofs")
        .iter()
        .enumerate()
    {
        let t = &d["terms"][2];
        close(t["largest_u"].as_f64().expect("u"), want[k], DOF_NAMES[k]);
        let source = t["source"].as_str().expect("source");
        assert!(
            source.starts_with("calibration id 1 (the run's; the run did not record its term, made now from the stored file): the linear fit's hold-out error h"),
            "{source}"
        );
        // The other unrecorded terms stay unrecorded.
        assert!(
            d["terms"][3]["source"]
                .as_str()
                .is_some_and(|s| s.starts_with("not recorded"))
        );
    }
}

/// A run whose record says a term is not stated: the report says so, with the reason the run
/// gave; a recorded map no longer in the store is named.
#[test]
fn a_term_the_run_could_not_state_is_named_with_its_reason() {
    let dir = TempDir::new("report-budget-unstated");
    let (db, _) = store(
        &dir,
        |_| {
            let mut r = recorded(99);
            r.calibration = Stated::NotStated("the calibration has no hold-out error".into());
            r.drift = Stated::NotStated("the service runs no drift check".into());
            serde_json::json!({ KEY: r.to_json() })
        },
        1,
        None,
    );
    let j = report_json(&db, &[]);
    let terms = &j["budget"]["dofs"][1]["terms"];
    let source = |i: usize| terms[i]["source"].as_str().expect("source").to_string();
    assert_eq!(
        source(2),
        "not stated: the calibration has no hold-out error"
    );
    assert_eq!(
        source(Component::Environment.index()),
        "not stated: the service runs no drift check"
    );
    assert!(
        source(3).contains("follower map id 99 \"stage-1.csv\", which is no longer in the store"),
        "{}",
        source(3)
    );
    for i in [
        2,
        3,
        Component::Bend.index(),
        Component::Environment.index(),
    ] {
        assert_eq!(terms[i]["largest_u"], 0.0, "{}", source(i));
    }
}

/// The service records the budget's inputs when it starts a run: the follower map in use (its
/// id, and the encoder's offset to the carriage, here against the twin's truth), the
/// calibration's term (none configured: not stated, and why), the drift check and the
/// temperature inputs as not stated, PSD2's sensitivities through its decoupling.
#[tokio::test(start_paused = true)]
async fn the_service_records_the_budget_inputs_when_a_run_starts() {
    use crate::helpers::{RigOptions, ServiceRig, short_plan};
    use axiscomp::evaluate::recorded::Recorded;
    use axiscomp::service::api::Request;
    let rig = ServiceRig::start(RigOptions {
        service_toml: "[align]\ncheck_before_run = false\n".into(),
        ..RigOptions::default()
    })
    .await;
    let cert = Certificate::parse(CERT, "stage.csv").expect("certificate");
    let map = follower::build(&[], Some(&cert), &MapSettings::default()).expect("map");
    let map_id = Store::open(&rig.store)
        .expect("store")
        .insert_follower_map(&map, "stage.csv", false)
        .expect("map");
    rig.request(Request::FollowerMap { id: Some(map_id) })
        .await
        .expect("map in use");
    // The carriage 1.5 mm on, the spot still on PSD2: the follower stays, its encoder reads
    // 1.5 mm less than the carriage.
    rig.twin
        .plant
        .move_carriage(1.5, axiscomp::util::clock::now());
    let settled = rig.twin.plant.carriage_move_end() + std::time::Duration::from_millis(500);
    tokio::time::sleep_until(settled.into()).await;
    let plant = &rig.twin.plant;
    let truth = plant.follower_encoder() - plant.carriage(axiscomp::util::clock::now()).0;
    assert!((truth + 1.5).abs() < 0.01, "the follower stayed: {truth}");
    let started = rig
        .request(Request::RunStart {
            plan: short_plan(),
            dialect: None,
            notes: None,
        })
        .await
        .expect("the run starts");
    rig.request(Request::RunAbort).await.expect("abort");
    let id = RunId(started["run_id"].as_i64().expect("run id"));
    let run = Store::open_read_only(&rig.store)
        .expect("store")
        .run(id)
        .expect("run");
    let Recorded::Yes(r) = Recorded::of_config(&run.config) else {
        panic!("no budget record: {}", run.config);
    };
    let Stated::Stated(m) = &r.follower_map else {
        panic!("{:?}", r.follower_map);
    };
    assert_eq!(
        (m.id, m.name.as_str(), m.source.as_str()),
        (map_id, "stage.csv", "certificate")
    );
    let offset = m.encoder_offset_mm.expect("the carriage was measured");
    assert!(
        (offset - truth).abs() < 0.1,
        "the encoder read {offset:.3} mm more than the carriage; the twin says {truth:.3} mm"
    );
    assert!(
        matches!(&r.calibration, Stated::NotStated(w) if w.starts_with("no calibration")),
        "{:?}",
        r.calibration
    );
    assert!(matches!(&r.drift, Stated::NotStated(w) if w.contains("no drift check")));
    assert!(matches!(&r.thermal, Stated::NotStated(w) if w.contains("temperature sensor")));
    // dy per mm of X2: 1 (X2 = dx + dy − 1.648·ez + …, dx from X3, ez from X1).
    let s = r.psd2_sensitivity.expect("sensitivities");
    assert!((s[1][0] - 1.0).abs() < 0.05, "{s:?}");
    assert!(
        (s[4][1] - 1.0 / 150.0).abs() < 0.05 / 150.0,
        "roll per mm of Y2: {s:?}"
    );
}

/// A run measured in the virtual-time lab (as the demo does: the follower mapped and its map
/// in use, a drift check, a calibration term), stored with `report::budget::record_lab_run`:
/// `axiscomp report` states every term but the temperature's (the twin has no sensor), and
/// its budget is the lab's own, term by term at every point.
#[test]
#[ignore = "a 200 mm lab run with the follower mapped (100 s unoptimised): run optimised by .ci/run"]
fn a_lab_run_stored_with_its_record_reports_the_labs_own_budget() {
    use axiscomp::comp::PositioningMode;
    use axiscomp::evaluate::ReferenceLine;
    use axiscomp::plc::CncMap;
    use axiscomp::run::program::CaptureMode;
    use axiscomp::run::{Capture, Dialect};
    use axiscomp::sim::InstallSpec;
    use axiscomp::sim::axis::AxisSpec;
    use axiscomp::sim::closed_loop::{self, BudgetSpec, LoopSpec, Pass};
    use axiscomp::sim::follower_cal::Mapping;
    use axiscomp::sim::lab::{Lab, LabSpec, plan_span};
    use axiscomp::sim::plant::PlantSpec;
    use std::time::Duration;
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    // The mapping as `lab::the_closed_loop_cuts_positioning_and_straightness_to_a_tenth`
    // makes it: two passes of 300 frames a side over 200 mm.
    let length_mm = 200.0;
    let plant = PlantSpec {
        seed: 5,
        install: InstallSpec {
            offset_mm: 0.0,
            tilt_deg: 0.0,
            gain_error: 0.0,
        },
        axis: AxisSpec {
            length_mm,
            ..AxisSpec::default()
        },
        ..PlantSpec::default()
    };
    let plan = crate::lab::plan(length_mm, 5, 2, 3000.0);
    let mut mapping = Mapping::over(plan_span(&plan));
    mapping.cal.passes = 2;
    mapping.cal.average_frames = 300;
    let mut budget = BudgetSpec::of_plant(&plant);
    budget.calibration = Some((
        std::array::from_fn(|k| CAL_U[k] / DOF_TO_USER[k]),
        "the study's hold-out".into(),
    ));
    budget.drift_check = Some(Duration::from_secs(20));
    let spec = LoopSpec {
        budget,
        lab: LabSpec::standard(plant, None).expect("spec"),
        plan,
        dialect: Dialect::LinuxCnc,
        mode: CaptureMode::Stability,
        positioning: PositioningMode::Bidirectional,
        straightness_line: ReferenceLine::LeastSquares,
        map: CncMap::generic().expect("generic map"),
        step_mm: None,
        zero_window: Duration::from_millis(500),
        align_rounds: 0,
        follower: Some(mapping),
    };
    let mut lab = Lab::new(&spec.lab).expect("lab");
    let mapped = closed_loop::prepare(&mut lab, &spec, &mut |_| {})
        .expect("bring-up and mapping")
        .expect("a map");
    let m = closed_loop::measure(&mut lab, &spec, Pass::Before, &mut |_| {}).expect("run");

    // Stored as the demo stores its runs, then the record.
    let dir = TempDir::new("report-budget-lab");
    let db = dir.path("axiscomp.db");
    let mut store = Store::open(&db).expect("store");
    let id = store
        .create_run(&NewRun {
            axis: "X".into(),
            plan: serde_json::to_value(&spec.plan).expect("plan"),
            config: serde_json::json!({"twin": "test", "pass": "before"}),
            calibration: None,
            notes: "lab".into(),
        })
        .expect("run");
    store.set_run_state(id, RunState::Running).expect("state");
    let caps: Vec<Capture> = m.run.captures.iter().map(|c| c.capture).collect();
    for c in &caps {
        store.insert_capture(id, c).expect("capture");
    }
    for h in &m.run.handovers {
        store.insert_handover(Some(id), h).expect("handover");
    }
    store.set_run_state(id, RunState::Finished).expect("state");
    axiscomp::report::budget::record_lab_run(&mut store, id, &m.budget.inputs, Some(&mapped.map))
        .expect("record");
    drop(store);
    if let Ok(keep) = std::env::var("REPORT_KEEP") {
        let _ = std::fs::copy(&db, std::path::Path::new(&keep).join("lab-budget.db"));
    }

    let j = report_json(&db, &[]);
    let mut compared = 0;
    for (k, d) in j["budget"]["dofs"]
        .as_array()
        .expect("dofs")
        .iter()
        .enumerate()
    {
        let sources: Vec<&str> = d["terms"]
            .as_array()
            .expect("terms")
            .iter()
            .map(|t| t["source"].as_str().expect("source"))
            .collect();
        for (i, s) in sources.iter().enumerate() {
            // Only the temperature terms are not stated: the twin's axis has no sensor.
            let thermal = i == Component::ThermalTemperature.index()
                || i == Component::ThermalCoefficient.index();
            assert_eq!(s.starts_with("not"), thermal, "term {i}: {s}");
        }
        assert!(
            sources[3].contains("the lab's follower map (self-calibration"),
            "{}",
            sources[3]
        );
        for p in d["points"].as_array().expect("points") {
            let x = p["target_mm"].as_f64().expect("target");
            let dir = match p["direction"].as_str().expect("direction") {
                "+" => Some(Direction::Up),
                "-" => Some(Direction::Down),
                _ => None,
            };
            let own = m
                .budget
                .points
                .iter()
                .find(|q| q.dof == k && (q.position_mm - x).abs() < 1e-9 && q.direction == dir)
                .expect("the lab's point");
            let user = DOF_TO_USER[k];
            for c in axiscomp::evaluate::uncertainty::Component::ALL {
                let got = p["terms"][c.name()].as_f64().expect("term");
                close(
                    got,
                    own.terms[c.index()] * user,
                    &format!("{} at {x} mm {dir:?}: {}", DOF_NAMES[k], c.name()),
                );
            }
            close(p["U"].as_f64().expect("U"), own.expanded * user, "U");
            compared += 1;
        }
    }
    assert_eq!(compared, m.budget.points.len());
    // The drift check and the follower term are not zero: they were stated, not defaulted.
    let dy = &j["budget"]["dofs"][1]["terms"];
    assert!(dy[3]["largest_u"].as_f64().expect("follower") > 0.0);
    assert!(
        dy[Component::Environment.index()]["largest_u"]
            .as_f64()
            .expect("drift")
            > 0.0
    );
}

/// End to end: a run the service measured on the twin (its CNC running the part program)
/// with a follower map in use; `axiscomp report` states the follower term from the map the
/// run recorded — S·√(u(x)² + u(ref)²) with the certificate's 0.2 µm — and says why the
/// calibration and drift terms are not stated.
#[tokio::test(start_paused = true)]
async fn a_service_run_reports_the_follower_map_it_used() {
    use crate::helpers::{RigOptions, ServiceRig, short_plan};
    use axiscomp::service::api::Request;
    use std::time::Duration;
    let rig = ServiceRig::start(RigOptions {
        service_toml: "[align]\ncheck_before_run = false\n\n\
                       [tracking]\nrest_ms = 200\naverage_frames = 100\nsettle_ms = 100\n\n\
                       [capture]\nframes = 100\nsettle_ms = 200\n"
            .into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    let cert = Certificate::parse(CERT, "stage.csv").expect("certificate");
    let map = follower::build(&[], Some(&cert), &MapSettings::default()).expect("map");
    let map_id = Store::open(&rig.store)
        .expect("store")
        .insert_follower_map(&map, "stage.csv", false)
        .expect("map");
    rig.request(Request::FollowerMap { id: Some(map_id) })
        .await
        .expect("map in use");
    rig.request(Request::Zero).await.expect("zero");
    let started = rig
        .request(Request::RunStart {
            plan: short_plan(),
            dialect: None,
            notes: None,
        })
        .await
        .expect("the run starts");
    let id = started["run_id"].as_i64().expect("run id");
    let t0 = axiscomp::util::clock::now();
    // The machine time the status states: so far while it runs (never more than the time
    // since it was started, and growing), then from its start to its end.
    let mut so_far = 0.0f64;
    let ended_s = loop {
        let st = rig.request(Request::RunStatus).await.expect("run status");
        let elapsed = axiscomp::util::clock::since(t0).as_secs_f64();
        match st["state"].as_str() {
            Some("running") => {
                let m = st["machine_s"].as_f64().expect("machine time so far");
                assert!(
                    m >= so_far && m <= elapsed + 1e-3,
                    "{m} s after {elapsed} s"
                );
                assert_eq!(st["resumed"], false);
                so_far = m;
            }
            Some("finished") => {
                let m = st["machine_time_s"].as_f64().expect("machine time");
                assert!(
                    m >= so_far && m <= elapsed + 1e-3,
                    "{m} s after {elapsed} s"
                );
                break m;
            }
            _ => panic!("the run ended so: {st}"),
        }
        assert!(
            axiscomp::util::clock::since(t0) < Duration::from_secs(240),
            "not finished: {st}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert!(so_far > 0.0 && ended_s > 0.0, "{so_far} s, {ended_s} s");
    let run = Store::open_read_only(&rig.store)
        .expect("store")
        .run(RunId(id))
        .expect("run");
    assert!((run.machine_time_s() - ended_s).abs() < 1e-6);
    let r = &run.config[KEY];
    let offset = r["follower_map"]["stated"]["encoder_offset_mm"]
        .as_f64()
        .expect("the carriage was measured at the start");
    let s_dy = r["psd2_sensitivity"][1][0].as_f64().expect("sensitivity");
    let o = bin()
        .args(["report", "--db", rig.store.to_str().expect("path"), "--run"])
        .arg(id.to_string())
        .arg("--json")
        .output()
        .expect("report");
    assert!(o.status.success(), "{}", stderr(&o));
    let j: serde_json::Value = serde_json::from_str(&stdout(&o)).expect("json");
    let dy = &j["budget"]["dofs"][1];
    let source = dy["terms"][3]["source"].as_str().expect("source");
    assert!(
        source.contains(&format!(
            "id {map_id} \"stage.csv\" (certificate), the run's"
        )),
        "{source}"
    );
    for p in dy["points"].as_array().expect("points") {
        let x = p["target_mm"].as_f64().expect("target");
        let want = s_dy * cert_u(x + offset).hypot(cert_u(offset));
        close(
            p["terms"]["follower map"].as_f64().expect("term"),
            want,
            "dy follower",
        );
    }
    let says = |i: usize| {
        dy["terms"][i]["source"]
            .as_str()
            .unwrap_or_default()
            .to_string()
    };
    assert!(
        says(2).starts_with("not stated: no calibration"),
        "{}",
        says(2)
    );
    assert!(
        says(Component::Environment.index())
            .starts_with("not stated: the service runs no drift check"),
        "{}",
        says(Component::Environment.index())
    );
}
