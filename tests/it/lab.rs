//! The virtual-time lab: whole runs of the measurement chain (I/O frames, the CANopen master
//! and the twin drive exchanging frames, tracking, the run machine, the CNC running the
//! generated program) on a simulated clock, compared with the plant's truth.

use axiscomp::evaluate::{EvalOptions, evaluate_captures};
use axiscomp::run::Direction;
use axiscomp::run::program::CaptureMode;
use axiscomp::run::{Dialect, Plan, PlanSpec};
use axiscomp::sim::InstallSpec;
use axiscomp::sim::lab::{Lab, LabSpec};
use axiscomp::sim::plant::PlantSpec;
use axiscomp::units::{DOF_NAMES, Errors6};
use std::collections::BTreeSet;
use std::time::Duration;

fn perfect_head(seed: u64) -> PlantSpec {
    PlantSpec {
        seed,
        install: InstallSpec {
            offset_mm: 0.0,
            tilt_deg: 0.0,
            gain_error: 0.0,
        },
        ..PlantSpec::default()
    }
}

pub(crate) fn plan(end_mm: f64, targets: usize, runs: u32, feed_mm_min: f64) -> Plan {
    Plan::new(PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm,
        targets,
        runs,
        overrun_mm: 2.0,
        dwell_s: 2.0,
        feed_mm_min,
        lead_mm: 10.0,
        reference_mm: None,
    })
    .expect("plan")
}

/// 0–40 mm, 5 targets, 2 bidirectional runs, stability capture: every stop is captured once,
/// at rest on its target, and each capture's six errors lie within 3 stated standard
/// uncertainties of the truth (relative to the zero reference at 0 mm). The lab is
/// deterministic (seeded noise, simulated clock): a pass is a pass every time.
#[test]
fn a_short_run_captures_every_stop_at_the_truth() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let spec = LabSpec::standard(perfect_head(3), None).expect("spec");
    let mut lab = Lab::new(&spec).expect("lab");
    lab.bring_up().expect("bring-up");
    let at_zero = lab.plant.truth(lab.now());
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    let plan = plan(40.0, 5, 2, 2000.0);
    let run = lab
        .measure(&plan, Dialect::LinuxCnc, CaptureMode::Stability, |_| {})
        .expect("run");
    assert_eq!(run.captures.len(), 20);
    let keys: BTreeSet<_> = run
        .captures
        .iter()
        .map(|c| (c.capture.run, c.capture.target_index, c.capture.direction))
        .collect();
    assert_eq!(keys.len(), 20, "a stop captured twice");
    let mut worst = [0.0f64; 6];
    for c in &run.captures {
        let (cap, truth) = (&c.capture, &c.truth);
        assert!(
            !truth.moving && (truth.travel - cap.target_mm).abs() < 1e-4,
            "capture {:?} not at rest on its target: {truth:?}",
            (cap.run, cap.target_index, cap.direction)
        );
        let (m, t, t0, u) = (
            cap.errors.to_array(),
            truth.errors.to_array(),
            at_zero.errors.to_array(),
            cap.u.to_array(),
        );
        for k in 0..6 {
            let z = (m[k] - (t[k] - t0[k])).abs() / u[k];
            worst[k] = worst[k].max(z);
            assert!(
                z <= 3.0,
                "{} at {} mm run {} {:?}: measured {:e}, truth {:e}, u {:e} ({z:.2} u)",
                DOF_NAMES[k],
                cap.target_mm,
                cap.run,
                cap.direction,
                m[k],
                t[k] - t0[k],
                u[k]
            );
        }
    }
    eprintln!("worst |measured − truth| / u per DOF: {worst:.2?}");
}

/// ISO 230-2's full test on the twin: a 1000 mm axis, 11 targets, 5 bidirectional runs,
/// stability capture, the reference head with the plant's default axis errors. At every
/// target and in each direction the measured mean deviation of every DOF lies within its
/// stated expanded uncertainty (k = 2) of the truth's mean over the same captures.
///
/// 340 s of machine time: about 3 min unoptimised, 20 s optimised; `.ci/run` runs it with
/// `cargo test --release --test it lab:: -- --ignored`.
#[test]
#[ignore = "a whole 1000 mm run: run optimised by .ci/run"]
fn a_1000_mm_axis_11_targets_5_runs_matches_the_truth_within_u() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let spec = LabSpec::standard(perfect_head(11), None).expect("spec");
    let mut lab = Lab::new(&spec).expect("lab");
    lab.bring_up().expect("bring-up");
    let at_zero = lab.plant.truth(lab.now()).errors.to_array();
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    let plan = plan(1000.0, 11, 5, 6000.0);
    let wall = std::time::Instant::now();
    let run = lab
        .measure(&plan, Dialect::LinuxCnc, CaptureMode::Stability, |_| {})
        .expect("run");
    eprintln!(
        "{} captures in {:.0} s simulated, {:.1} s wall; {} handovers",
        run.captures.len(),
        run.duration.as_secs_f64(),
        wall.elapsed().as_secs_f64(),
        run.handovers.len()
    );
    assert_eq!(run.captures.len(), 110);
    let captures: Vec<_> = run.captures.iter().map(|c| c.capture).collect();
    let eval = evaluate_captures(&captures, &EvalOptions::default()).expect("evaluation");
    let mut worst = [0.0f64; 6];
    let mut worst_ratio = [0.0f64; 6];
    for dir in [Direction::Up, Direction::Down] {
        for (i, &ti) in eval.target_indices.iter().enumerate() {
            // The truth's mean over the captures this mean is made of.
            let truths: Vec<[f64; 6]> = run
                .captures
                .iter()
                .filter(|c| c.capture.target_index == ti && c.capture.direction == dir)
                .map(|c| c.truth.errors.to_array())
                .collect();
            assert_eq!(truths.len(), 5);
            for k in 0..6 {
                let p = &eval.profiles[k];
                let (m, u) = match dir {
                    Direction::Up => (p.up.as_ref(), p.u_up.as_ref()),
                    Direction::Down => (p.down.as_ref(), p.u_down.as_ref()),
                };
                let (m, u) = (m.expect("profile")[i], u.expect("U")[i]);
                let t = truths.iter().map(|t| t[k] - at_zero[k]).sum::<f64>() / 5.0;
                let d = (m - t).abs();
                worst[k] = worst[k].max(d);
                worst_ratio[k] = worst_ratio[k].max(d / u);
                assert!(
                    d <= u,
                    "{} at {} mm {dir:?}: measured mean {m:e}, truth {t:e}, U {u:e}",
                    DOF_NAMES[k],
                    eval.positions_mm[i]
                );
            }
        }
    }
    let user = Errors6::from_array(worst).to_user();
    eprintln!(
        "max |measured − truth| per DOF (µm, µm, µm, ″, ″, ″): {user:.3?}; worst |measured − truth|/U: {worst_ratio:.2?}"
    );
}

/// Continuous following (the encoder strategy) in cyclic synchronous position: the carriage
/// runs 0 → 100 mm at 50 mm/s in one move; PSD2 keeps the spot throughout (within 1 mm of
/// its centre, of ±4.5 mm, while moving), and at rest the live six errors match the truth within 3
/// stated standard deviations, positioning included (its stitching uncertainty from the
/// follower's encoder).
#[test]
fn encoder_following_over_100_mm_in_one_move_matches_the_truth() {
    let _machine = crate::helpers::heavy();
    let mut spec = LabSpec::standard(perfect_head(5), None).expect("spec");
    spec.tracking.strategy = axiscomp::track::Strategy::Encoder;
    let mut lab = Lab::new(&spec).expect("lab");
    lab.bring_up().expect("bring-up");
    let at_zero = lab.plant.truth(lab.now()).errors.to_array();
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    lab.trace = Some(Vec::new());
    lab.move_carriage(100.0).expect("move");
    let trace = lab.trace.take().unwrap_or_default();
    let worst_x2 = trace
        .iter()
        .map(|r| r.psd2.map_or(f64::INFINITY, |p| p.0.abs()))
        .fold(0.0, f64::max);
    assert!(trace.len() > 1000, "{} frames traced", trace.len());

    lab.pipeline.measure.set_nominal(Some(100.0));
    lab.advance(spec.live_window + Duration::from_millis(100))
        .expect("window");
    let live = lab.pipeline.measure.live().expect("live errors");
    let truth = lab.plant.truth(lab.now()).errors.to_array();
    let (m, sd) = (live.errors.to_array(), live.sd.to_array());
    for k in 0..6 {
        let z = (m[k] - (truth[k] - at_zero[k])).abs() / sd[k];
        assert!(
            z <= 3.0,
            "{}: measured {:e}, truth {:e}, sd {:e} ({z:.2} sd)",
            DOF_NAMES[k],
            m[k],
            truth[k] - at_zero[k],
            sd[k]
        );
    }
    eprintln!(
        "PSD2 within {worst_x2:.4} mm of centre while moving; positioning sd {:.2} µm",
        sd[1] * 1e3
    );
}

/// Issue 5's closed loop at test size: a 200 mm axis with the twin's default errors (±30 µm
/// positioning with a 2 µm ball-screw periodic term and 5 µm backlash, ±20 µm straightness)
/// is measured, its tables are published into the twin's PLC over Modbus TCP, and the
/// verification run shows E, M and both straightnesses at a tenth of their values before.
/// The truth agrees: the compensated plant's own errors at the captures are as small.
#[test]
fn the_closed_loop_cuts_positioning_and_straightness_to_a_tenth() {
    closed_loop_case(200.0, 6, 2, 2.0);
}

/// The same at full size: 1000 mm, 11 targets, 5 bidirectional runs (run optimised by
/// `.ci/run`, about 5 s; 3 min unoptimised).
#[test]
#[ignore = "a whole 1000 mm loop: run optimised by .ci/run"]
fn the_closed_loop_on_a_1000_mm_axis_cuts_the_errors_to_a_tenth() {
    closed_loop_case(1000.0, 11, 5, 5.0);
}

fn closed_loop_case(length_mm: f64, targets: usize, runs: u32, step_mm: f64) {
    use axiscomp::comp::PositioningMode;
    use axiscomp::evaluate::ReferenceLine;
    use axiscomp::plc::CncMap;
    use axiscomp::sim::axis::AxisSpec;
    use axiscomp::sim::closed_loop::{self, Figures, LoopSpec};
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let mut plant = perfect_head(5);
    plant.axis = AxisSpec {
        length_mm,
        ..AxisSpec::default()
    };
    let spec = LoopSpec {
        lab: LabSpec::standard(plant, None).expect("spec"),
        plan: plan(length_mm, targets, runs, 3000.0),
        dialect: Dialect::LinuxCnc,
        mode: CaptureMode::Stability,
        positioning: PositioningMode::Bidirectional,
        straightness_line: ReferenceLine::LeastSquares,
        map: CncMap::generic().expect("generic map"),
        // A fine grid: the PLC's linear interpolation then reproduces the measured profile
        // at the (irregular) targets.
        step_mm: Some(step_mm),
        zero_window: Duration::from_millis(500),
        align_rounds: 0,
    };
    let r = closed_loop::run(&spec, |_| {}).expect("the loop");
    let (b, a) = (r.before.figures, r.after.figures);
    let um = |x: f64| x * 1000.0;
    eprintln!(
        "{length_mm} mm: E {:.2} → {:.2} µm, M {:.2} → {:.2} µm, R {:.2?} → {:.2?}, straightness x {:.2} → {:.2} µm, z {:.2} → {:.2} µm",
        um(b.e),
        um(a.e),
        um(b.m),
        um(a.m),
        b.r.map(um),
        a.r.map(um),
        um(b.straightness_x),
        um(a.straightness_x),
        um(b.straightness_z),
        um(a.straightness_z)
    );
    // The same figures of the plant's truth at the captures of the verification run.
    let truths: Vec<_> = r
        .after
        .run
        .captures
        .iter()
        .map(|c| {
            let mut cap = c.capture;
            cap.errors = c.truth.errors;
            cap
        })
        .collect();
    let t = Figures::of(
        &evaluate_captures(&truths, &EvalOptions::default()).expect("truth evaluation"),
        ReferenceLine::LeastSquares,
    );
    eprintln!(
        "truth after: E {:.2} µm, M {:.2} µm, straightness x {:.2} µm, z {:.2} µm",
        um(t.e),
        um(t.m),
        um(t.straightness_x),
        um(t.straightness_z)
    );
    assert_eq!(r.published.len(), 3, "positioning and both straightnesses");
    assert!(
        b.e > 20e-3 && b.m > 20e-3 && b.straightness_x > 10e-3 && b.straightness_z > 10e-3,
        "the axis had errors to compensate: {b:?}"
    );
    for (name, before, after, truth) in [
        ("E", b.e, a.e, t.e),
        ("M", b.m, a.m, t.m),
        (
            "straightness x",
            b.straightness_x,
            a.straightness_x,
            t.straightness_x,
        ),
        (
            "straightness z",
            b.straightness_z,
            a.straightness_z,
            t.straightness_z,
        ),
    ] {
        assert!(
            after <= 0.1 * before,
            "{name}: {:.2} µm after, {:.2} µm before",
            um(after),
            um(before)
        );
        // The measurement's own systematic error (the follower's errors between handovers,
        // stated in the stitching uncertainty) stays in the compensated axis: the truth is
        // judged by the same tenth.
        assert!(
            truth <= 0.1 * before,
            "{name}: truth {:.2} µm after, {:.2} µm before",
            um(truth),
            um(before)
        );
    }
}
