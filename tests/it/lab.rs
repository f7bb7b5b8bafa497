//! The virtual-time lab: whole runs of the measurement chain (I/O frames, the CANopen master
//! and the twin drive exchanging frames, tracking, the run machine, the CNC running the
//! generated program) on a simulated clock, compared with the plant's truth.

use axiscomp::run::program::CaptureMode;
use axiscomp::run::{Dialect, Plan, PlanSpec};
use axiscomp::sim::InstallSpec;
use axiscomp::sim::lab::{Lab, LabSpec};
use axiscomp::sim::plant::PlantSpec;
use axiscomp::units::DOF_NAMES;
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

fn plan(end_mm: f64, targets: usize, runs: u32) -> Plan {
    Plan::new(PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm,
        targets,
        runs,
        overrun_mm: 2.0,
        dwell_s: 2.0,
        feed_mm_min: 2000.0,
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
    let spec = LabSpec::standard(perfect_head(3), None).expect("spec");
    let mut lab = Lab::new(&spec).expect("lab");
    lab.bring_up().expect("bring-up");
    let at_zero = lab.plant.truth(lab.now());
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    let plan = plan(40.0, 5, 2);
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
