//! The follower error map (issue 14): the twin's follower mapped by the stop-and-go
//! self-calibration on the virtual-time lab and by its certificate, compared with the twin's
//! true follower errors; the map applied in tracking, compared with the truth; certificates
//! with bad rows refused with the line named.

use axiscomp::follower::{self, Certificate, Direction, FollowerMap, MapSettings, Source, Step};
use axiscomp::run::Dialect;
use axiscomp::run::program::CaptureMode;
use axiscomp::sim::Rng;
use axiscomp::sim::follower::{FollowerSpec, Motion};
use axiscomp::sim::follower_cal::{CalSpec, LevelSpec, reference_level, self_calibrate};
use axiscomp::sim::lab::{Lab, LabSpec, plan_span};
use axiscomp::sim::plant::PlantSpec;
use std::sync::Arc;
use std::time::Duration;

fn motion(d: Direction) -> Motion {
    match d {
        Direction::Up => Motion::Up,
        Direction::Down => Motion::Down,
    }
}

/// A lab on an axis of `length_mm` (the follower's travel is the axis'), brought up.
fn lab(seed: u64, length_mm: f64) -> Lab {
    lab_and_spec(seed, length_mm).0
}

/// The same with the lab's spec (its decoupler and live window, for the level's line).
fn lab_and_spec(seed: u64, length_mm: f64) -> (Lab, LabSpec) {
    lab_with(seed, length_mm, FollowerSpec::default())
}

/// The same with the follower `follower` (the head at its nominal layout, so the nominal
/// decoupling is exact and the rail is what is judged).
fn lab_with(seed: u64, length_mm: f64, follower: FollowerSpec) -> (Lab, LabSpec) {
    let mut plant = PlantSpec {
        seed,
        follower,
        ..PlantSpec::default()
    };
    plant.axis.length_mm = length_mm;
    plant.install.offset_mm = 0.0;
    plant.install.tilt_deg = 0.0;
    let spec = LabSpec::standard(plant, None).expect("spec");
    let mut lab = Lab::new(&spec).expect("lab");
    lab.bring_up().expect("bring-up");
    (lab, spec)
}

/// How the map compares with the twin's truth.
struct Compared {
    /// Per vertical point: position (mm), map − truth (µm, both to their end-point lines),
    /// stated u (µm).
    vertical: Vec<(f64, f64, f64)>,
    /// Largest |map − truth| / u along the axis (differences from the first point, both
    /// directions, every mm), and the largest |map − truth| (µm).
    along_ratio: f64,
    along_worst_um: f64,
    /// The share of those within 2 u.
    along_within_2u: f64,
}

fn compare(lab: &Lab, map: &FollowerMap) -> Compared {
    let m = &lab.plant.follower;
    let vp = &map.vertical_positions_mm;
    let (x0, x1) = (vp[0], vp[vp.len() - 1]);
    // Without a level the map is the straightness to its end-point line; with the level's
    // stations, the whole vertical relative to its first point.
    let referenced = map.vertical_reference.is_some();
    let line = |x: f64| {
        if referenced {
            m.vertical(x0)
        } else {
            m.vertical(x0) + (m.vertical(x1) - m.vertical(x0)) * (x - x0) / (x1 - x0)
        }
    };
    let vertical = vp
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let truth = m.vertical(x) - line(x);
            (
                x,
                (map.vertical_mm[i] - truth) * 1e3,
                map.vertical_u_mm[i] * 1e3,
            )
        })
        .collect();
    let (mut along_ratio, mut along_worst_um) = (0.0f64, 0.0f64);
    let (mut within, mut total) = (0usize, 0usize);
    let p0 = map.point(x0, Direction::Up);
    let t0 = m.along(x0, Motion::Up);
    let mut x = x0;
    while x <= x1 {
        for dir in [Direction::Up, Direction::Down] {
            let p = map.point(x, dir);
            let got = p.along_um - p0.along_um;
            let want = (m.along(x, motion(dir)) - t0) * 1e3;
            let u = p.along_u_um.hypot(p0.along_u_um);
            along_ratio = along_ratio.max((got - want).abs() / u);
            total += 1;
            within += usize::from((got - want).abs() <= 2.0 * u);
            along_worst_um = along_worst_um.max((got - want).abs());
        }
        x += 1.0;
    }
    Compared {
        vertical,
        along_ratio,
        along_worst_um,
        along_within_2u: within as f64 / total.max(1) as f64,
    }
}

/// Map the twin's follower over `length_mm`: the stop-and-go pass, its certificate, and with
/// `level` (the lab's spec) the vertical line from a level at both ends, as the product's
/// procedure does (`follower_cal::map_on_lab`).
fn map_follower(
    lab: &mut Lab,
    span: (f64, f64),
    cal: CalSpec,
    level: Option<&LabSpec>,
) -> (FollowerMap, Vec<Step>) {
    let cal = CalSpec {
        from_mm: span.0,
        to_mm: span.1,
        ..cal
    };
    let run = self_calibrate(lab, &cal, |_, _| {}).expect("self-calibration");
    let cert_text = lab.plant.follower.certificate(&mut Rng::new(99));
    let cert = Certificate::parse(&cert_text, "twin-certificate.csv").expect("certificate");
    let mut map = follower::build(&run.steps, Some(&cert), &MapSettings::default()).expect("map");
    if let Some(spec) = level {
        let reference = reference_level(
            lab,
            &map,
            span,
            &LevelSpec::default(),
            &spec.decoupler,
            spec.live_window,
        )
        .expect("the level's stations");
        map = follower::build_referenced(
            &run.steps,
            Some(&cert),
            &MapSettings::default(),
            Some(&reference),
        )
        .expect("map with the level");
    }
    if let Some(s) = map.self_calibration.as_mut() {
        s.machine_time_s = Some(run.machine_time.as_secs_f64());
    }
    eprintln!(
        "self-calibration: {} steps ({} skipped), {:.1} min of machine time",
        run.steps.len(),
        run.skipped,
        run.machine_time.as_secs_f64() / 60.0
    );
    for l in map.summary() {
        eprintln!("  {l}");
    }
    (map, run.steps)
}

fn check_map(lab: &Lab, map: &FollowerMap, steps: &[Step]) {
    assert_eq!(map.sources.long, Source::Certificate);
    assert_eq!(map.sources.periodic, Source::SelfCalibration);
    assert_eq!(map.sources.reversal, Source::SelfCalibration);
    assert_eq!(map.sources.vertical, Source::SelfCalibration);
    // Each step's stated variance against what it really missed the truth by: PSD2's
    // vertical jump minus the twin's true v(to) − v(from) and the fitted slope's share.
    let m = &lab.plant.follower;
    let step_z: Vec<f64> = steps
        .iter()
        .map(|st| {
            let truth = m.vertical(st.to_mm) - m.vertical(st.from_mm)
                + map.vertical_slope * (st.to_mm - st.from_mm);
            (st.vertical_mm - truth) / st.variance[1].sqrt()
        })
        .collect();
    let step_rms = rms(&step_z);
    let c = compare(lab, map);
    let (mut worst, mut worst_ratio, mut max_u) = (0.0f64, 0.0f64, 0.0f64);
    let mut within = 0usize;
    let mut z = Vec::new();
    for &(x, err, u) in &c.vertical {
        eprintln!("  vertical at {x:8.2} mm: map − truth {err:+.3} µm, u {u:.3} µm");
        worst = worst.max(err.abs());
        max_u = max_u.max(u);
        if u > 0.0 {
            worst_ratio = worst_ratio.max(err.abs() / u);
            z.push(err / u);
        }
        within += usize::from(err.abs() <= 2.0 * u + 1e-6);
    }
    let share = within as f64 / c.vertical.len().max(1) as f64;
    let map_rms = rms(&z);
    eprintln!(
        "steps: {} of them, RMS of (step − truth)/its sd {step_rms:.2}; vertical: max |map − truth| {worst:.3} µm, largest u {max_u:.3} µm, RMS (map − truth)/u {map_rms:.2}, worst {worst_ratio:.2} u (the map's band {:.2} u), {:.1} % within 2 u; along: max |map − truth| {:.3} µm, worst /u {:.2}",
        steps.len(),
        map.vertical_band_k().unwrap_or(0.0),
        share * 100.0,
        c.along_worst_um,
        c.along_ratio
    );
    // The steps' stated variances are what they really scatter by about the truth: over
    // ~1200 steps the RMS of an honest z is 1 ± 0.03.
    assert!(
        (0.8..=1.25).contains(&step_rms),
        "the steps' stated sd is off: RMS z {step_rms:.2} over {} steps",
        steps.len()
    );
    // The map's points are not independent: all are relative to the first (with a level, all
    // share the first station's error) and neighbours share the walk between them, so one
    // map's share within 2 u or its worst point is one draw of a correlated curve. With the
    // walk of seed 2026 held and 200 fresh draws of its stations, an honest u gave an RMS z of
    // 1.00 (99th percentile 1.78), a worst point of 2.5 u (99th percentile 3.7 u) and a share
    // within 2 u as low as 57 %. So the u is judged by the RMS of z over the curve, below 2
    // (a u stated half what it is gives 2 and more), and every point within the band the map
    // states for the whole curve at once (k ≈ 3.7 u for ~270 points).
    assert!(
        map_rms <= 2.0,
        "vertical map: RMS (map − truth)/u {map_rms:.2} over {} points",
        z.len()
    );
    let band = map.vertical_band_k().expect("a vertical map");
    assert!(
        worst_ratio <= band,
        "vertical map: a point {worst_ratio:.2} u from the truth, outside the map's band of {band:.2} u"
    );
    // Along the axis, as the certificate's own coverage: 95 % of the points within 2 u (k = 2),
    // none beyond 4 u.
    assert!(
        c.along_within_2u >= 0.95 && c.along_ratio <= 4.0,
        "along-axis map: {:.1} % within 2 u, worst {:.2} u",
        c.along_within_2u * 100.0,
        c.along_ratio
    );
    let truth_rev = lab.plant.follower.spec.reversal_um;
    let r = map.reversal.expect("reversal");
    assert!(
        (r.value_mm * 1e3 - truth_rev).abs() <= 2.0 * r.u_mm * 1e3 + 0.02,
        "reversal {:.3} µm, truth {truth_rev} µm",
        r.value_mm * 1e3
    );
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// Max and RMS |measured − truth| of positioning (µm) and roll (″) over a run's captures.
fn run_errors(
    lab: &mut Lab,
    map: Option<Arc<FollowerMap>>,
    length_mm: f64,
    targets: usize,
    runs: u32,
) -> [(f64, f64); 2] {
    lab.pipeline.tracker.set_map(map);
    lab.move_carriage(0.0).expect("to 0");
    let at_zero = lab.plant.truth(lab.now()).errors.to_array();
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    let plan = crate::lab::plan(length_mm, targets, runs, 6000.0);
    let run = lab
        .measure(&plan, Dialect::LinuxCnc, CaptureMode::Stability, |_| {})
        .expect("run");
    let mut out = [(0.0f64, 0.0f64); 2];
    for (slot, (k, scale)) in [
        (1usize, 1e3),
        (4usize, 180.0 * 3600.0 / std::f64::consts::PI),
    ]
    .into_iter()
    .enumerate()
    {
        let errs: Vec<f64> = run
            .captures
            .iter()
            .map(|c| {
                let (m, t) = (c.capture.errors.to_array(), c.truth.errors.to_array());
                (m[k] - (t[k] - at_zero[k])) * scale
            })
            .collect();
        let max = errs.iter().fold(0.0f64, |a, e| a.max(e.abs()));
        let rms = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
        out[slot] = (max, rms);
    }
    out
}

fn case(seed: u64, length_mm: f64, cal: CalSpec, targets: usize, runs: u32) {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let (mut lab, spec) = lab_and_spec(seed, length_mm);
    let plan = crate::lab::plan(length_mm, targets, runs, 6000.0);
    let span = plan_span(&plan);
    let (map, steps) = map_follower(&mut lab, span, cal, Some(&spec));
    check_map(&lab, &map, &steps);
    let without = run_errors(&mut lab, None, length_mm, targets, runs);
    let with = run_errors(&mut lab, Some(Arc::new(map)), length_mm, targets, runs);
    eprintln!(
        "{length_mm} mm run, |measured − truth| max / RMS: positioning {:.3} / {:.3} µm without the map, {:.3} / {:.3} µm with; roll {:.3} / {:.3}″ without, {:.3} / {:.3}″ with",
        without[0].0,
        without[0].1,
        with[0].0,
        with[0].1,
        without[1].0,
        without[1].1,
        with[1].0,
        with[1].1
    );
    assert!(with[0].1 < without[0].1, "positioning RMS not improved");
    assert!(with[1].1 < without[1].1, "roll RMS not improved");
}

/// At test size: a 120 mm axis, two passes of 300 frames a side; the map against the twin's
/// truth, then a run with the map closer to the truth than without.
#[test]
fn the_followers_map_matches_its_truth_and_improves_tracking() {
    case(
        21,
        120.0,
        CalSpec {
            passes: 2,
            average_frames: 300,
            probe_every: 7,
            ..CalSpec::default()
        },
        5,
        2,
    );
}

/// The same on a 1000 mm axis at the demo's settings (four passes of 1000 frames a side, the
/// level's stations), 11 targets, 2 runs, on two twins. Seed 2026's map: RMS z 1.30, worst
/// 3.19 u at 444 mm, 90.3 % of its 268 points within 2 u (the first station read 0.05 µm
/// low, 1.3 of its u, and every point carries it); seed 7's: RMS z 0.97, worst 2.31 u.
#[test]
#[ignore = "two 1000 mm self-calibrations at the demo's settings: run optimised by .ci/run"]
fn the_followers_map_over_1000_mm() {
    for seed in [2026, 7] {
        case(seed, 1000.0, CalSpec::default(), 11, 2);
    }
}

/// A certificate with a bad row is refused, naming the file and the line.
#[test]
fn certificates_with_bad_rows_are_refused_with_the_line() {
    let h = "# vendor\nposition_mm,error_um,direction,uncertainty_um\n";
    for (body, line, what) in [
        (
            "0,0.1,+,0.2\n10,0.2,+,0.2\n10,0.3,+,0.2\n",
            5,
            "not above the previous + row's 10 mm",
        ),
        (
            "0,0.1,+,0.2\n10,0.2,,0.2\n",
            4,
            "column direction: empty field: write + or -",
        ),
        (
            "0,0.1,+,0.2\n10,NaN,+,0.2\n",
            4,
            "column error_um: \"NaN\" is not a finite number",
        ),
        ("0,0.1,+,0.2\n10,0.2,+\n", 4, "3 fields, the header has 4"),
        (
            "0,0.1,+,0.2\n10,0.2,+,0.2,7\n",
            4,
            "5 fields, the header has 4",
        ),
        (
            "0,0.1,+,0.2\n10,0.2,x,0.2\n",
            4,
            "column direction: \"x\" is neither + nor -",
        ),
    ] {
        let e = Certificate::parse(&format!("{h}{body}"), "cert.csv")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with(&format!("cert.csv line {line}")), "{e}");
        assert!(e.contains(what), "{e}");
    }
    // The twin's own certificate reads back.
    let lab_model =
        axiscomp::sim::follower::FollowerModel::new(Default::default(), 300.0, &mut Rng::new(1));
    let c = Certificate::parse(&lab_model.certificate(&mut Rng::new(2)), "twin.csv").unwrap();
    assert_eq!((c.up.len(), c.down.len()), (33, 33));
}

const GOOD_CERT: &str = "# vendor\nposition_mm,error_um,direction,uncertainty_um\n0,0.0,+,0.2\n10,1.0,+,0.2\n20,1.5,+,0.2\n0,0.5,-,0.2\n10,1.5,-,0.2\n20,2.0,-,0.2\n";

/// `axiscomp follower import|show`: a bad certificate exits 2 naming the file and line and
/// stores nothing; a good one is stored, in use, and exported as TOML that reads back as the
/// map built from it, and as CSV.
#[test]
fn the_command_line_imports_shows_and_exports() {
    use crate::helpers::{TempDir, run, stderr, stdout};
    let dir = TempDir::new("follower-cli");
    let db = dir.path("store.db");
    let db_s = db.display().to_string();
    let bad = dir.write(
        "bad.csv",
        "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n10,1,,0.2\n",
    );
    let o = run(
        &[
            "follower",
            "import",
            &bad.display().to_string(),
            "--db",
            &db_s,
        ],
        "",
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains(&format!(
            "{} line 3, column direction: empty field",
            bad.display()
        )),
        "{err}"
    );
    let good = dir.write("vendor.csv", GOOD_CERT);
    let o = run(
        &[
            "follower",
            "import",
            &good.display().to_string(),
            "--db",
            &db_s,
        ],
        "",
    );
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("from the certificate"),
        "{}",
        stdout(&o)
    );
    let (toml, csv) = (dir.path("map.toml"), dir.path("map.csv"));
    let o = run(
        &[
            "follower",
            "show",
            "--db",
            &db_s,
            "--toml",
            &toml.display().to_string(),
            "--csv",
            &csv.display().to_string(),
            "--step-mm",
            "5",
        ],
        "",
    );
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(
        out.lines()
            .any(|l| l.starts_with("*   1 ") && l.contains("certificate")),
        "{out}"
    );
    let cert = Certificate::parse(GOOD_CERT, &good.display().to_string()).unwrap();
    let want = follower::build(&[], Some(&cert), &MapSettings::default()).unwrap();
    let got = FollowerMap::from_toml(&std::fs::read_to_string(&toml).unwrap(), "map.toml").unwrap();
    assert_eq!(got, want);
    let csv = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(
        rows[0],
        "position_mm,along_up_um,along_down_um,along_u_um,vertical_um,vertical_u_um"
    );
    // 10 mm: +1.0 µm up, +1.5 µm down (the certificate's own directions), u 0.2 µm.
    assert_eq!(rows[3], "10.000,1.000,1.500,0.200,0.000,0.000");
}

/// The service: a stored map put in use by the control request is applied and named in the
/// snapshot; viewers may ask which map is in use.
#[tokio::test(start_paused = true)]
async fn the_service_puts_a_stored_map_in_use_and_shows_it() {
    use crate::helpers::{RigOptions, ServiceRig};
    use axiscomp::service::api::Request;
    let rig = ServiceRig::start(RigOptions::default()).await;
    let cert = Certificate::parse(GOOD_CERT, "vendor.csv").unwrap();
    let map = follower::build(&[], Some(&cert), &MapSettings::default()).unwrap();
    let id = {
        let mut store = axiscomp::store::Store::open(&rig.store).expect("store");
        store
            .insert_follower_map(&map, "vendor.csv", false)
            .expect("insert")
    };
    let r = rig
        .request(Request::FollowerMap { id: None })
        .await
        .expect("show");
    assert!(r["in_use"].is_null(), "{r}");
    assert_eq!(r["maps"][0]["name"], "vendor.csv");
    let r = rig
        .request(Request::FollowerMap { id: Some(id) })
        .await
        .expect("use");
    assert_eq!(r["in_use"]["id"], id);
    assert_eq!(r["in_use"]["sources"]["long"], "certificate");
    let s = rig
        .wait_for(10, "the map in the snapshot", |s| {
            s.tracking.follower_map.is_some()
        })
        .await;
    let v = s.tracking.follower_map.expect("map view");
    assert_eq!(
        (v.id, v.name.as_str(), v.source.as_str()),
        (id, "vendor.csv", "certificate")
    );
    let e = rig
        .request(Request::FollowerMap { id: Some(id + 7) })
        .await
        .unwrap_err();
    assert!(
        e.to_string()
            .contains(&format!("follower map {} is not in the store", id + 7)),
        "{e}"
    );
    rig.stop().await;
}

/// The map alone on a 1000 mm axis with a lighter pass (two passes, 300 frames a side):
/// `cargo test --test it follower::the_followers_map_alone -- --ignored --nocapture`.
#[test]
#[ignore = "a 1000 mm self-calibration: 20 min of machine time"]
fn the_followers_map_alone_over_1000_mm_two_light_passes() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let mut lab = lab(2026, 1000.0);
    let cal = CalSpec {
        passes: 2,
        average_frames: 300,
        ..CalSpec::default()
    };
    let (map, steps) = map_follower(&mut lab, (-2.0, 1002.0), cal, None);
    check_map(&lab, &map, &steps);
}

/// Issue 26: the instrument's map, made once on its bench, re-used on a machine where the rail
/// only bends with the bed: the level's stations take the bend in, and the map in tracking is
/// the rail's true vertical on this set-up within its stated u; on a machine where the rail
/// was kinked, the check refuses the map and names the span.
#[test]
fn the_instruments_map_is_reused_on_a_bent_set_up_and_refused_on_a_kinked_rail() {
    use axiscomp::follower::ReuseError;
    use axiscomp::sim::follower::Kink;
    use axiscomp::sim::follower_cal::{MapTwinError, map_instrument, reuse_on_lab};
    let length = 400.0;
    let cal = CalSpec {
        from_mm: -2.0,
        to_mm: length + 2.0,
        passes: 2,
        ..CalSpec::default()
    };
    let level = LevelSpec {
        station_mm: 50.0,
        ..LevelSpec::default()
    };
    for instrument in [3, 4] {
        let own = FollowerSpec {
            instrument_seed: Some(instrument),
            bend_um: 3.0,
            ..FollowerSpec::default()
        };
        let bench = map_instrument(own, length, &cal, |_, _| {}).expect("the bench's map");
        let machine = |seed: u64, follower: FollowerSpec| {
            let (mut lab, spec) = lab_with(seed, length, follower);
            let got = reuse_on_lab(
                &mut lab,
                &bench,
                (cal.from_mm, cal.to_mm),
                &level,
                &spec.decoupler,
                spec.live_window,
            );
            (lab, got)
        };
        for seed in [40 + instrument, 50 + instrument] {
            let (lab, got) = machine(seed, own);
            let m = got.unwrap_or_else(|e| panic!("instrument {instrument}, seed {seed}: {e}"));
            let check = m.map.reuse.clone().expect("the check kept with the map");
            assert!(check.bend_range_mm > 0.1e-3, "{}", check.describe());
            // Against the rail's true vertical on this set-up (bend and all), relative to
            // the map's first point (the head at its nominal layout and aligned: PSD2's
            // vertical against the beam is the rail's). The stored map alone would be off by
            // the bend.
            let truth = |x: f64| lab.plant.follower.vertical(x);
            let off_line = |map: &FollowerMap| {
                let x0 = map.vertical_positions_mm[0];
                (1..=40)
                    .map(|k| {
                        let x = k as f64 * length / 40.0;
                        let got = map.correction(x, Direction::Up)[1]
                            - map.correction(x0, Direction::Up)[1];
                        let u = map.point(x, Direction::Up).vertical_u_um * 1e-3;
                        (x, got - (truth(x) - truth(x0)), u)
                    })
                    .collect::<Vec<_>>()
            };
            let reused = off_line(&m.map);
            let worst = reused.iter().map(|p| p.1.abs()).fold(0.0, f64::max);
            for &(x, d, u) in &reused {
                assert!(
                    d.abs() < 4.0 * u.max(0.02e-3),
                    "instrument {instrument}, seed {seed} at {x} mm: {:+.3} µm off the truth (u {:.3} µm); {}",
                    d * 1e3,
                    u * 1e3,
                    check.describe()
                );
            }
            let worst_bench = off_line(&bench.map)
                .iter()
                .map(|p| p.1.abs())
                .fold(0.0, f64::max);
            assert!(
                worst_bench > (2.0 * worst).max(0.3e-3),
                "the test can tell: the bench's map alone is {:.3} µm off, the re-used {:.3} µm",
                worst_bench * 1e3,
                worst * 1e3
            );
        }
        // The rail kinked by 25 µrad (5″) at 230 mm on this machine: refused, the span
        // named. (Over 400 mm a kink of 10 µrad stays within a cubic bend to 0.1 µm, inside
        // the stations' noise: what a check of this many stations cannot see.)
        let kinked = FollowerSpec {
            kink: Some(Kink {
                at_mm: 230.0,
                urad: 25.0,
            }),
            ..own
        };
        let (_, got) = machine(60 + instrument, kinked);
        match got {
            Err(MapTwinError::Reuse(e @ ReuseError::Changed { from_mm, to_mm, .. })) => {
                assert!(from_mm <= 230.0 && to_mm >= 230.0, "{e}");
                assert!(e.to_string().contains("map the follower again"), "{e}");
            }
            Err(e) => panic!("instrument {instrument}: refused for another reason: {e}"),
            Ok(m) => panic!(
                "instrument {instrument}: the kinked rail passed: {}",
                m.map.reuse.map(|c| c.describe()).unwrap_or_default()
            ),
        }
    }
}
