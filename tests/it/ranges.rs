//! Every number checked where it is read: configuration keys, twin keys, map keys, CSV
//! columns and plan fields out of range are refused with the key (or the column and line) and
//! the accepted range, never a panic. The sweeps set each float of a shipped file in turn to
//! the extremes (1e-300, 1e300, inf, nan, -1); the fixtures pin the messages.

use crate::helpers::{TempDir, run, stderr};
use std::path::Path;

/// What every float is set to in turn (TOML's `inf` and `nan` included).
const EXTREMES: [f64; 5] = [1e-300, 1e300, f64::INFINITY, f64::NAN, -1.0];

/// Every float of `t` (in nested tables and arrays): its dotted key and its place.
fn floats(t: &toml::Table, prefix: &str, out: &mut Vec<(String, Vec<Step>)>, at: &mut Vec<Step>) {
    for (k, v) in t {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        at.push(Step::Key(k.clone()));
        match v {
            toml::Value::Float(_) => out.push((key, at.clone())),
            toml::Value::Table(inner) => floats(inner, &key, out, at),
            toml::Value::Array(items) => {
                for (i, x) in items.iter().enumerate() {
                    if x.is_float() {
                        at.push(Step::Index(i));
                        out.push((key.clone(), at.clone()));
                        at.pop();
                    }
                }
            }
            _ => {}
        }
        at.pop();
    }
}

#[derive(Clone, Debug)]
enum Step {
    Key(String),
    Index(usize),
}

/// `t` with the float at `at` set to `x`.
fn with_float(t: &toml::Table, at: &[Step], x: f64) -> toml::Table {
    let mut t = t.clone();
    let mut v: &mut toml::Value = match &at[0] {
        Step::Key(k) => &mut t[k.as_str()],
        Step::Index(_) => unreachable!("a table's first step is a key"),
    };
    for s in &at[1..] {
        v = match s {
            Step::Key(k) => &mut v[k.as_str()],
            Step::Index(i) => &mut v[*i],
        };
    }
    *v = toml::Value::Float(x);
    t
}

/// Every float of `text` at every extreme: (key, value, the file's text).
fn extreme_cases(text: &str) -> Vec<(String, f64, String)> {
    let table: toml::Table = text.parse().expect("TOML");
    let mut found = Vec::new();
    floats(&table, "", &mut found, &mut Vec::new());
    assert!(!found.is_empty());
    found
        .iter()
        .flat_map(|(key, at)| {
            let table = &table;
            EXTREMES.iter().map(move |&x| {
                let text = toml::to_string(&with_float(table, at, x)).expect("TOML out");
                (key.clone(), x, text)
            })
        })
        .collect()
}

fn repo_text(path: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(path)).expect(path)
}

/// `axiscomp check --config FILE` with each float of `configs/axiscomp.toml` at each extreme:
/// accepted (0) or refused (2) naming the key and the range, never a panic (101). The files
/// are checked by parallel processes (a few hundred, about 30 ms each).
#[test]
fn check_accepts_or_refuses_every_float_of_the_shipped_config() {
    let t0 = std::time::Instant::now();
    // The example names a calibration file that exists only on an installed machine.
    let base = repo_text("configs/axiscomp.toml").replace(
        "calibration = \"/var/lib/axiscomp/calibration.toml\"",
        "calibration = \"\"",
    );
    let dir = TempDir::new("ranges-check");
    let base_file = dir.write("base.toml", &base);
    let o = run(&["check", "--config", base_file.to_str().unwrap()], "");
    assert!(o.status.success(), "the base passes: {}", stderr(&o));
    let cases = extreme_cases(&base);
    let files: Vec<(String, f64, std::path::PathBuf)> = cases
        .into_iter()
        .enumerate()
        .map(|(i, (key, x, text))| (key, x, dir.write(&format!("case-{i}.toml"), &text)))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results: Vec<(usize, Option<i32>, String)> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..6)
            .map(|_| {
                s.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some((_, _, file)) = files.get(i) else {
                            return out;
                        };
                        let o = run(&["check", "--config", file.to_str().unwrap()], "");
                        out.push((i, o.status.code(), stderr(&o)));
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|w| w.join().expect("worker"))
            .collect()
    });
    assert_eq!(results.len(), files.len());
    let mut refused = 0;
    for (i, code, err) in &results {
        let (key, x, _) = &files[*i];
        let case = format!("{key} = {x}: exit {code:?}, stderr: {err}");
        assert!(!err.contains("panicked") && *code != Some(101), "{case}");
        match code {
            Some(0) => {}
            Some(2) => {
                refused += 1;
                let last = err.lines().last().unwrap_or_default();
                assert!(last.contains(&format!("{key}:")), "names the key: {case}");
                assert!(
                    last.contains(" use ") || last.contains("give"),
                    "says what to do: {case}"
                );
                assert!(!last.contains("Some(") && !last.contains("NaN"), "{case}");
            }
            _ => panic!("accepted (0) or refused (2): {case}"),
        }
    }
    // inf, nan and 1e300 are refused everywhere; the first two panics found are pinned.
    assert!(
        refused >= 3 * files.len() / 5,
        "{refused} of {}",
        files.len()
    );
    for (key, x, message) in [
        (
            "service.snapshot_hz",
            1e-300,
            "service.snapshot_hz: 1e-300 Hz is out of range: use 0.1 to 100 Hz",
        ),
        (
            "align.valid_for_h",
            1e300,
            "align.valid_for_h: 1e300 h is out of range: use 0.1 to 8760 h",
        ),
    ] {
        let (i, _, err) = results
            .iter()
            .find(|(i, _, _)| files[*i].0 == key && files[*i].1 == x)
            .expect("case");
        assert!(err.trim_end().ends_with(message), "{i}: {err}");
    }
    eprintln!(
        "check: {} cases ({} floats × {}), {refused} refused, in {:.1} s",
        files.len(),
        files.len() / EXTREMES.len(),
        EXTREMES.len(),
        t0.elapsed().as_secs_f64()
    );
}

/// The twin's `configs/sim.toml` (its hexapod too) with each float at each extreme: read or
/// refused naming the key and the range.
#[test]
fn every_float_of_the_twin_config_is_checked() {
    let mut refused = 0;
    let cases = extreme_cases(&repo_text("configs/sim.toml"));
    for (key, x, text) in &cases {
        let r = axiscomp::sim::config::parse(text, "sim.toml")
            .map(drop)
            .map_err(|e| e.to_string())
            .and_then(|()| {
                axiscomp::sim::hexapod_servers::spec_from_config(text, "sim.toml").map(drop)
            });
        if let Err(e) = r {
            refused += 1;
            assert!(e.contains(&format!("sim.toml: {key}:")), "{key} = {x}: {e}");
            assert!(
                e.contains(" use ") || e.contains("give"),
                "{key} = {x}: {e}"
            );
        }
    }
    assert!(
        refused >= 3 * cases.len() / 5,
        "{refused} of {}",
        cases.len()
    );
    let text = repo_text("configs/sim.toml");
    for (from, to, message) in [
        (
            "thermal_um_per_m_per_h = 0.0",
            "thermal_um_per_m_per_h = nan",
            "twin.axis.thermal_um_per_m_per_h: nan is not a number: use -1000 to 1000 µm/m/h",
        ),
        (
            "feed_mm_s = 50.0",
            "feed_mm_s = 0.0",
            "twin.carriage.feed_mm_s: 0 mm/s is out of range: use 0.1 to 2000 mm/s",
        ),
        (
            "start_mm = 2.0",
            "start_mm = -inf",
            "twin.follower.start_mm: -inf mm is out of range: use -10000 to 10000 mm",
        ),
        (
            "gear_ratio = 1.0",
            "gear_ratio = 1e300",
            "drive.gear_ratio: 1e300 is out of range: use 0.001 to 1000",
        ),
    ] {
        let e = axiscomp::sim::config::parse(&text.replace(from, to), "sim.toml")
            .map(drop)
            .unwrap_err()
            .to_string();
        assert!(e.ends_with(message), "{e}");
    }
    let e = axiscomp::sim::hexapod_servers::spec_from_config(
        &text.replace("speed_deg_s = 1.0", "speed_deg_s = 5e-324"),
        "sim.toml",
    )
    .unwrap_err();
    assert!(
        e.ends_with(
            "hexapod.speed_deg_s: 5e-324 degrees/s is out of range: use 0.001 to 1000 degrees/s"
        ),
        "{e}"
    );
}

/// Keys the float sweep does not reach (durations in ms and s, counts) and the refusals
/// whose message is worth pinning, each with its message.
#[test]
fn configuration_numbers_out_of_range_say_the_range() {
    let dir = TempDir::new("ranges-config");
    for (text, message) in [
        (
            "[head]\nlive_window_ms = 9223372036854775807",
            "head.live_window_ms: 9223372036854775807 ms is out of range: use 10 to 60000 ms",
        ),
        (
            "[follower]\nsync_ms = 5000",
            "follower.sync_ms: 5000 ms is out of range: use 1 to 1000 ms",
        ),
        (
            "[follower]\nvelocity_mm_s = 1e-300",
            "follower.velocity_mm_s: 1e-300 mm/s is out of range: use 0.001 to 1000 mm/s",
        ),
        (
            "[io]\nrate_hz = 0.5",
            "io.rate_hz: 0.5 Hz is out of range: use 0 (as fast as the module answers) or 1 to 10000 Hz",
        ),
        (
            "[tracking]\naverage_frames = 9223372036854775807",
            "tracking.average_frames: 9223372036854775807 is out of range: use 2 to 1000000",
        ),
        (
            "[capture]\ntimeout_s = 0",
            "capture.timeout_s: 0 s is out of range: use 1 to 86400 s",
        ),
        (
            "[plc]\nstep_mm = 1e-300",
            "plc.step_mm: 1e-300 mm is out of range: use 0 (the targets' mean spacing) or 0.01 to 10000 mm",
        ),
        (
            "[hexapod]\nwork = [0.0, 0.0, 0.0, 0.0, 1e300, 0.0]",
            "hexapod.work: v = 1e300 degrees is out of range: use -180 to 180 degrees",
        ),
        (
            "[hexapod]\nmotion_timeout_s = 0",
            "hexapod.motion_timeout_s: 0 s is out of range: use 1 to 86400 s",
        ),
        (
            "[hexapod]\nspeed_mm_s = inf",
            "hexapod.speed_mm_s: inf mm/s is out of range: use 0 (the controller's) or 0.001 to 1000 mm/s",
        ),
        (
            "[comp.fanuc]\ninput_increment_mm = 1e-300",
            "comp.fanuc.input_increment_mm: 1e-300 mm is out of range: use 1e-6 to 1 mm",
        ),
        (
            "[acceptance]\npitch_arcsec = 1e300",
            "acceptance.pitch_arcsec: 1e300 arcsec is out of range: use 0 (not specified) or 0.01 to 3600 arcsec",
        ),
        (
            "[machine]\nexpansion_um_per_m_k = 1e-300",
            "machine.expansion_um_per_m_k: 1e-300 µm/(m·K) is not an expansion coefficient",
        ),
    ] {
        let file = dir.write("bad.toml", &format!("{text}\n"));
        let e = axiscomp::config::load(&axiscomp::config::Layers {
            etc: None,
            file: Some(file),
            env: vec![],
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("bad.toml") && e.contains(message), "{text}: {e}");
    }
}

/// The map fixtures that carry a number out of range: refused with the file, the key and the
/// range.
#[test]
fn map_numbers_out_of_range_say_the_range() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let refusal = |dir: &str, file: &str| {
        let path = fixtures.join(dir).join(file);
        match dir {
            "io-maps" => axiscomp::acquire::IoMap::load(&path)
                .map(drop)
                .unwrap_err()
                .to_string(),
            _ => axiscomp::plc::CncMap::load(&path)
                .map(drop)
                .unwrap_err()
                .to_string(),
        }
    };
    for (dir, file, message) in [
        (
            "io-maps",
            "huge-gain.toml",
            "`psd[1].gain_x_mm_per_v`: 1e300 mm/V is out of range: use -1000 to -0.001 or 0.001 to 1000 mm/V",
        ),
        (
            "io-maps",
            "subnormal-scale.toml",
            "`psd[0].x.volts_per_count`: 1e-300 V is out of range: use -10 to -1e-9 or 1e-9 to 10 V",
        ),
        (
            "io-maps",
            "infinite-threshold.toml",
            "`sum_threshold_v`: inf V is out of range: use 0 to 100 V; give the SUM (V) below which a PSD has no spot",
        ),
        (
            "io-maps",
            "nan-offset.toml",
            "`psd[2].offset_y_mm`: nan is not a number: use -100 to 100 mm",
        ),
        (
            "cnc-maps",
            "scale-subnormal.toml",
            "`header.start.scale`: 1e-300 um per count is out of range: use 1 nm to 1 mm per count",
        ),
        (
            "cnc-maps",
            "max-step-huge.toml",
            "`limits.max_step_um`: 1e300 µm is out of range: use 0.001 to 10000 µm",
        ),
        (
            "cnc-maps",
            "max-abs-negative.toml",
            "`limits.max_abs_um`: -1 µm is out of range: use 0.001 to 10000 µm",
        ),
    ] {
        let e = refusal(dir, file);
        assert!(e.contains(file) && e.contains(message), "{e}");
    }
}

/// CSV numbers out of range: the file, the line and the column, and the range.
#[test]
fn csv_numbers_out_of_range_name_line_and_column() {
    let header = "dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec,X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um,travel_mm";
    let poses = |rows: &str| {
        let text = format!("{header}\n{rows}");
        axiscomp::calibrate::parse_pose_csv(&text, "poses.csv")
            .map(drop)
            .unwrap_err()
            .to_string()
    };
    let e = poses("0,0,0,0,0,0,1,2,3,4,5,6,0\n0,0,0,0,0,0,1,2,1e300,4,5,6,0\n");
    let want = "poses.csv line 3, column X2_um: 1e300 µm is out of range: use -100000 to 100000 µm";
    assert!(e.ends_with(want), "{e}");
    let e = poses("0,0,0,0,0,0,1,2,3,4,5,6,-1e300\n");
    let want = "line 2, column travel_mm: -1e300 mm is out of range: use -10000 to 10000 mm";
    assert!(e.ends_with(want), "{e}");

    let cert = "position_mm,error_um,direction,uncertainty_um\n0,0.5,+,0.2\n";
    for (row, message) in [
        (
            "100,1e300,+,0.2",
            "cert.csv line 3, column error_um: 1e300 µm is out of range: use -10000 to 10000 µm",
        ),
        (
            "1e300,0,+,0.2",
            "cert.csv line 3, column position_mm: 1e300 mm is out of range: use -10000 to 10000 mm",
        ),
        (
            "100,0,+,1e300",
            "cert.csv line 3, column uncertainty_um: 1e300 µm is out of range: use 0.001 to 1000 µm",
        ),
    ] {
        let e = axiscomp::follower::Certificate::parse(&format!("{cert}{row}\n"), "cert.csv")
            .unwrap_err()
            .to_string();
        assert_eq!(e, message);
    }

    let plan = "x_mm,y_mm,z_mm,u_deg,v_deg,w_deg,travel_mm\n0,0,0,0,0,0,0\n0,0,0,0,0,1e300,0\n";
    let e = axiscomp::hexapod::plan::PosePlan::parse(plan, "plan.csv")
        .unwrap_err()
        .to_string();
    assert_eq!(
        e,
        "plan.csv line 3, column w_deg: 1e300 degrees is out of range: use -180 to 180 degrees"
    );

    let e = axiscomp::evaluate::input::parse_deviation_csv(
        "target_index,target_mm,run,direction,deviation_um\n0,0,1,+,1e300\n",
        "captures.csv",
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("captures.csv line 2, column deviation_um: 1e300 µm is out of range: use -10000 to 10000 µm"),
        "{e}"
    );

    // The command line's CSV on standard input: refused with exit 2.
    let readings =
        "X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um,follower_mm\n0,0,0,0,0,0,5e-324\n1,2,3,4,5,6,1e300\n";
    let o = run(&["decouple", "--simulated"], readings);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    let want = "standard input line 3, column follower_mm: 1e300 mm is out of range: use -10000 to 10000 mm";
    assert!(err.contains(want), "{err}");
}

/// Plans: an ISO 230-2 plan's and the self-calibration's numbers out of range name the field.
#[test]
fn plan_numbers_out_of_range_name_the_field() {
    use axiscomp::follower::selfcal::{Plan as SelfCal, Spec};
    use axiscomp::run::{Plan, PlanSpec};
    let iso = |edit: &dyn Fn(&mut PlanSpec)| {
        let mut spec = PlanSpec::default();
        edit(&mut spec);
        Plan::new(spec).unwrap_err().to_string()
    };
    let refused = [
        iso(&|s| s.feed_mm_min = 1e-300),
        iso(&|s| s.targets = usize::MAX),
        iso(&|s| s.runs = u32::MAX),
        iso(&|s| s.start_mm = -1e300),
        iso(&|s| s.reference_mm = Some(f64::NAN)),
    ];
    let max = usize::MAX;
    assert_eq!(
        refused,
        [
            "test plan: feed_mm_min: 1e-300 mm/min is out of range: use 1 to 100000 mm/min".into(),
            format!("test plan: targets: {max} is out of range: use 5 to 1000"),
            "test plan: runs: 4294967295 is out of range: use 2 to 100".into(),
            "test plan: start_mm: -1e300 mm is out of range: use -10000 to 10000 mm".into(),
            "test plan: reference_mm: nan is not a number: use -10000 to 10000 mm".into(),
        ]
    );
    let selfcal = |spec: Spec| SelfCal::new(spec).unwrap_err().to_string();
    let d = Spec::default();
    assert_eq!(
        selfcal(Spec {
            from_mm: -1e300,
            to_mm: 1e300,
            ..d
        }),
        "self-calibration: from_mm -1e300 mm is out of range: use -10000 to 10000 mm"
    );
    assert_eq!(
        selfcal(Spec { passes: max, ..d }),
        format!("self-calibration: passes {max} is out of range: use 0 to 100")
    );
}
