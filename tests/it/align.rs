//! Long axes on any head: the twin's head mounted by eye (within 0.3° and 2 mm), aligned from
//! the spots at both ends of the travel, checked before a run starts, and runs that pause —
//! never fail — when a spot is lost, on the virtual clock and judged by the twin's truth.

use axiscomp::decouple::{Decoupler, Method, SolveOptions, Source};
use axiscomp::optics::Layout;
use axiscomp::run::program::CaptureMode;
use axiscomp::run::{Dialect, Plan, TargetKey};
use axiscomp::sim::InstallSpec;
use axiscomp::sim::axis::AxisSpec;
use axiscomp::sim::follower::FollowerSpec;
use axiscomp::sim::lab::{Lab, LabError, LabRun, LabSpec, plan_span};
use axiscomp::sim::plant::{MountSpec, Plant, PlantEvent, PlantSpec, Truth};
use std::collections::BTreeSet;
use std::time::Duration;

/// A lab whose head has the twin's random installation errors, is decoupled with its true
/// installation (as after a good calibration: the subject here is the mount), and is
/// mounted on a `length_mm` axis by eye, or exactly when `mount` is `None`.
fn lab(seed: u64, length_mm: f64, mount: Option<MountSpec>) -> Lab {
    lab_with(seed, length_mm, mount, InstallSpec::default())
}

fn lab_with(seed: u64, length_mm: f64, mount: Option<MountSpec>, install: InstallSpec) -> Lab {
    let plant = PlantSpec {
        seed,
        axis: AxisSpec {
            length_mm,
            ..AxisSpec::default()
        },
        install,
        mount: mount.unwrap_or_default(),
        ..PlantSpec::default()
    };
    let head = Plant::draw_head(&Layout::reference(), &plant).expect("head");
    let decoupler = Decoupler {
        source: Source::Model(head.truth.clone()),
        method: Method::Nonlinear,
        sigma_mm: [plant.noise_mm; 6],
        options: SolveOptions::default(),
    };
    let spec = LabSpec::standard(plant, Some(decoupler)).expect("spec");
    let mut lab = Lab::new(&spec).expect("lab");
    lab.bring_up().expect("bring-up");
    lab
}

/// A plan over 0..`end_mm` at 6000 mm/min (the lab tests' plan).
fn plan(end_mm: f64, targets: usize, runs: u32) -> Plan {
    crate::lab::plan(end_mm, targets, runs, 6000.0)
}

fn measure(lab: &mut Lab, plan: &Plan) -> Result<LabRun, LabError> {
    lab.measure(plan, Dialect::LinuxCnc, CaptureMode::Stability, |_| {})
}

/// Every capture of the plan exactly once, each at rest on its target, and its positioning
/// and angles within `k` stated standard uncertainties of the truth (relative to the truth
/// at the zero reference). Straightness is left out: a mount's residual angle adds a slope
/// (the ISO 230-1 line removes it), which is not the head's error.
fn assert_complete_and_true(run: &LabRun, plan: &Plan, at_zero: &Truth, k: f64, what: &str) {
    assert_complete(run, plan, what);
    for c in &run.captures {
        let (cap, truth) = (&c.capture, &c.truth);
        let (m, t, t0, u) = (
            cap.errors.to_array(),
            truth.errors.to_array(),
            at_zero.errors.to_array(),
            cap.u.to_array(),
        );
        for i in [1, 3, 4, 5] {
            let z = (m[i] - (t[i] - t0[i])).abs() / u[i];
            assert!(
                z <= k,
                "{what}: DOF {i} at {}: measured {:e}, truth {:e} ({z:.1} u)",
                TargetKey::of(cap).describe(plan),
                m[i],
                t[i] - t0[i]
            );
        }
    }
}

/// Every capture of the plan exactly once, each at rest on its target.
fn assert_complete(run: &LabRun, plan: &Plan, what: &str) {
    let keys: BTreeSet<TargetKey> = run
        .captures
        .iter()
        .map(|c| TargetKey::of(&c.capture))
        .collect();
    assert_eq!(
        run.captures.len(),
        plan.capture_count(),
        "{what}: captures taken"
    );
    assert_eq!(keys.len(), plan.capture_count(), "{what}: a capture twice");
    for c in &run.captures {
        let (cap, truth) = (&c.capture, &c.truth);
        assert!(
            !truth.moving && (truth.travel - cap.target_mm).abs() < 1e-4,
            "{what}: {} not at rest on its target",
            TargetKey::of(cap).describe(plan)
        );
    }
}

/// The largest |measured − truth| of the positioning (µm), relative to the zero reference.
fn worst_positioning_um(run: &LabRun, at_zero: &Truth) -> f64 {
    run.captures
        .iter()
        .map(|c| (c.capture.errors.dy - (c.truth.errors.dy - at_zero.errors.dy)).abs() * 1e3)
        .fold(0.0, f64::max)
}

/// The same with the follower stage's own along-axis error taken out (µm): the twin knows
/// where PSD2 really is against its encoder. The head reads the stage's error change since
/// the run's first capture (at the reference, where the stitch is re-referenced) as
/// positioning, with the opposite sign. What is left is the head's own: alignment and noise.
fn worst_positioning_without_follower_um(run: &LabRun) -> f64 {
    let own = |t: &Truth| t.follower_true - t.follower_encoder;
    let Some(first) = run.captures.first() else {
        return 0.0;
    };
    run.captures
        .iter()
        .map(|c| {
            let truth = c.truth.errors.dy - first.truth.errors.dy;
            let follower = own(&c.truth) - own(&first.truth);
            (c.capture.errors.dy - first.capture.errors.dy - truth + follower).abs() * 1e3
        })
        .fold(0.0, f64::max)
}

/// Align, zero at the plan's reference, measure; returns the run, the truth at the zero and
/// the rounds the alignment took.
fn aligned_run(lab: &mut Lab, plan: &Plan, what: &str) -> (LabRun, Truth, usize) {
    let rounds = lab
        .align(plan_span(plan), 8, |_| {})
        .unwrap_or_else(|e| panic!("{what}: {e}"));
    let last = &rounds.last().expect("a round").advice;
    assert!(last.now.passed(), "{what}: {}", last.now);
    lab.move_carriage(plan.reference_mm)
        .expect("to the reference");
    let at_zero = lab.truth();
    lab.zero(plan.reference_mm, Duration::from_millis(500))
        .expect("zero");
    let run = measure(lab, plan).unwrap_or_else(|e| panic!("{what}: {e}"));
    (run, at_zero, rounds.len())
}

/// Must show 1: 50 seeds × 500, 1000 and 2000 mm, each head mounted by eye. Aligned, every
/// run completes with every capture once, at rest on its target, the beam within 400 µrad of
/// the travel and the positioning within 1 µm of the truth beside the unmapped follower's own
/// error (which the twin knows). Not aligned, the pre-run check refuses (or, for a
/// mount that happens to be good enough, the run completes): never a run failing half-way.
#[test]
#[ignore = "300 labs on long axes: run optimised by .ci/run"]
fn fifty_seeds_on_500_1000_2000_mm_axes_align_and_complete_or_are_refused() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let mut summary = Vec::new();
    for length in [500.0, 1000.0, 2000.0] {
        // The shortest plan the service accepts: five targets per metre, at least five; two
        // runs.
        let plan = plan(length, ((length / 200.0).ceil() as usize).max(5), 2);
        let (mut refused, mut lucky, mut rounds_max) = (0, 0, 0);
        let mut worst_angle_urad = 0.0_f64;
        let mut worst_dy_um = 0.0_f64;
        let mut worst_own_um = 0.0_f64;
        for seed in 1..=50u64 {
            let what = format!("seed {seed}, {length} mm");
            let mut raw = lab(seed, length, Some(MountSpec::by_eye()));
            match measure(&mut raw, &plan) {
                Err(LabError::Refused { check }) => {
                    assert!(check.contains("PSD"), "{what}: {check}");
                    assert!(check.contains("turn the"), "{what}: {check}");
                    refused += 1;
                }
                Ok(run) => {
                    assert_eq!(run.captures.len(), plan.capture_count(), "{what}");
                    lucky += 1;
                }
                Err(e) => {
                    panic!("{what}: not aligned, the run failed instead of being refused: {e}")
                }
            }
            let mut lab = lab(seed, length, Some(MountSpec::by_eye()));
            let (run, at_zero, rounds) = aligned_run(&mut lab, &plan, &what);
            rounds_max = rounds_max.max(rounds);
            let m = lab.plant.mount();
            let angle = m.yaw.abs().max(m.pitch.abs());
            // The check passes at 200 µrad measured by the corner cube, which sees the
            // factory's own residual too.
            assert!(
                angle < 400e-6,
                "{what}: the beam is {angle:e} rad off the travel"
            );
            worst_angle_urad = worst_angle_urad.max(angle * 1e6);
            assert_complete(&run, &plan, &what);
            // Unmapped (these labs do not map their follower: issue 14 does), the head reads
            // the stage's own along-axis error as positioning: within its span in the twin
            // (long shape ±4 µm, screw ±1 µm, reversal 1 µm: 11 µm). Taken out, the head is
            // within its noise of the truth.
            let dy = worst_positioning_um(&run, &at_zero);
            let spec = FollowerSpec::default();
            let span = 2.0 * (spec.positioning_um + spec.periodic_um) + spec.reversal_um;
            assert!(dy < span, "{what}: positioning {dy:.1} µm from the truth");
            worst_dy_um = worst_dy_um.max(dy);
            let own = worst_positioning_without_follower_um(&run);
            assert!(
                own < 1.0,
                "{what}: positioning {own:.2} µm from the truth beside the follower's own error"
            );
            worst_own_um = worst_own_um.max(own);
            assert!(lab.pauses.is_empty(), "{what}: {:?}", lab.pauses);
        }
        summary.push(format!(
            "{length} mm: 50/50 aligned and complete (at most {rounds_max} rounds, beam within {worst_angle_urad:.0} µrad of the travel, positioning at most {worst_dy_um:.1} µm from the truth, {worst_own_um:.2} µm beside the unmapped follower's own error); not aligned: {refused} refused, {lucky} good enough as mounted"
        ));
    }
    eprintln!("{}", summary.join("\n"));
}

/// Must show 3a: every beam blocked for 30 s in the middle of a run. The run pauses (the
/// program stops at its next stop), goes on when the beams are back, and ends with every
/// capture exactly once, each at the truth. (A head without installation errors: overlap
/// stitching reads a rotated PSD2's cross-talk as a vertical step, which is the follower's
/// subject, not the pause's.)
#[test]
fn a_beam_blocked_for_30_s_pauses_the_run_and_it_resumes_with_every_capture_once() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let exact = InstallSpec {
        offset_mm: 0.0,
        tilt_deg: 0.0,
        gain_error: 0.0,
    };
    let mut lab = lab_with(3, 1000.0, None, exact);
    let plan = plan(40.0, 5, 2);
    lab.pre_run_check(&plan).expect("the check passes");
    lab.move_carriage(0.0).expect("home");
    let at_zero = lab.truth();
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    // 15 s into the run (the second target of the first run): everything dark for 30 s.
    let t = lab.now() + Duration::from_secs(15);
    lab.plant.schedule(t, PlantEvent::Block([true; 3]));
    lab.plant
        .schedule(t + Duration::from_secs(30), PlantEvent::Block([false; 3]));
    let run = measure(&mut lab, &plan);
    let run = run.unwrap_or_else(|e| panic!("{e}; pauses: {:?}", lab.pauses));
    assert_eq!(lab.pauses.len(), 1, "{:?}", lab.pauses);
    let why = &lab.pauses[0];
    assert!(
        why.contains("PSD1, PSD2, PSD3 have no spot") && why.contains("paused"),
        "{why}"
    );
    assert!(lab.extra_programs >= 1, "the rest of the cycle was sent");
    assert_complete_and_true(&run, &plan, &at_zero, 3.0, "blocked 30 s");
}

/// Must show 3b: the head knocked on its mount in the middle of a 1000 mm run. The spot
/// leaves its PSD, the run pauses naming the PSD; the technician realigns (the targets show
/// the beam off the PSD, not blocked) and takes the zero again, and the run finishes with
/// every capture exactly once.
#[test]
#[ignore = "a 1000 mm run with a realignment in it: run optimised by .ci/run"]
fn a_knocked_mount_pauses_the_run_naming_the_psd_and_it_finishes_after_realignment() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    let mut lab = lab(21, 1000.0, Some(MountSpec::by_eye()));
    let plan = plan(1000.0, 5, 2);
    lab.align(plan_span(&plan), 8, |_| {}).expect("aligned");
    lab.move_carriage(0.0).expect("home");
    lab.zero(0.0, Duration::from_millis(500)).expect("zero");
    let t = lab.now() + Duration::from_secs(40);
    lab.plant.schedule(
        t,
        PlantEvent::Knock(axiscomp::align::Mount {
            yaw: 1e-3,
            x: 3.0,
            ..Default::default()
        }),
    );
    let run = measure(&mut lab, &plan).expect("the run finishes");
    assert!(!lab.pauses.is_empty());
    let why = &lab.pauses[0];
    assert!(why.contains("PSD1") || why.contains("PSD3"), "{why}");
    let keys: BTreeSet<TargetKey> = run
        .captures
        .iter()
        .map(|c| TargetKey::of(&c.capture))
        .collect();
    assert_eq!(run.captures.len(), plan.capture_count());
    assert_eq!(keys.len(), plan.capture_count());
    // Realigned: the beam is back within a few hundred µrad of the travel.
    let m = lab.plant.mount();
    assert!(m.yaw.abs() < 1e-3 && m.pitch.abs() < 1e-3, "{m:?}");
    // Nothing was captured with the head knocked: every capture's mount is the aligned one
    // before the knock or the realigned one after.
    for c in &run.captures {
        let m = c.truth.mount;
        assert!(
            m.x.abs() < 1.5 && m.yaw.abs() < 1e-3,
            "{} taken with the head knocked: {m:?}",
            TargetKey::of(&c.capture).describe(&plan)
        );
    }
}

/// Must show 2 in small: the demo's path (align from the spots, then the check) on a 2000 mm
/// axis for a few seeds in plain `cargo test`, against the truth.
#[test]
fn a_2000_mm_axis_is_aligned_from_the_spots_at_both_ends() {
    crate::helpers::init_test_log();
    let _machine = crate::helpers::heavy();
    for seed in [12, 14] {
        let mut lab = lab(seed, 2000.0, Some(MountSpec::by_eye()));
        let before = lab.plant.mount();
        let rounds = lab.align((-2.0, 2002.0), 8, |_| {}).expect("aligned");
        let after = lab.plant.mount();
        // The first round saw the mount as it was: the advice's misalignment, when PSD3 was
        // read at both ends, is the twin's true beam angle.
        let last = &rounds.last().expect("a round").advice;
        assert!(last.now.passed(), "seed {seed}: {}", last.now);
        let [yaw, pitch] = last.misalignment_urad.expect("PSD3 read at both ends");
        assert!(
            (yaw.abs() - after.yaw.abs() * 1e6).abs() < 60.0
                && (pitch.abs() - after.pitch.abs() * 1e6).abs() < 60.0,
            "seed {seed}: reported {yaw:.0}/{pitch:.0} µrad, truth {:.0}/{:.0} µrad",
            after.yaw * 1e6,
            after.pitch * 1e6
        );
        assert!(
            before.yaw.abs().max(before.pitch.abs()) > 5e-4,
            "seed {seed}: mounted too well to prove anything: {before:?}"
        );
        assert!(
            after.yaw.abs() < 5e-4 && after.pitch.abs() < 5e-4,
            "{after:?}"
        );
    }
}

/// The service's alignment over its control API, against the real-time twin: the technician
/// (this test) jogs the carriage to each end, reads the station, enters what a target shows
/// where a PSD has no spot, and turns the twin's screws as advised, until the check passes;
/// the beam's residual angle the service reports is the twin's.
#[tokio::test(start_paused = true)]
async fn the_service_advises_the_screw_turns_until_the_check_passes() {
    use crate::helpers::{RigOptions, ServiceRig};
    use axiscomp::align::Screw;
    use axiscomp::service::api::{FollowerAction, Request};

    let defaults = RigOptions::default();
    let rig = ServiceRig::start(RigOptions {
        plant: PlantSpec {
            seed: 5,
            mount: MountSpec {
                angle_deg: 0.15,
                offset_mm: 0.5,
            },
            feed: 100.0,
            ..defaults.plant
        },
        ..RigOptions::default()
    })
    .await;
    let span = (0.0, 400.0);
    // Whatever the draw: the head is knocked 4 mrad in yaw, 1 mrad in pitch (the follower found
    // its spot at start-up; the far end is off the PSDs).
    rig.twin.plant.knock(axiscomp::align::Mount {
        yaw: 4e-3,
        pitch: -1e-3,
        ..Default::default()
    });
    let before = rig.twin.plant.mount();
    // 10..390 mm with 5 mm of overrun: the travel is the span aligned.
    let run_start = || Request::RunStart {
        plan: axiscomp::run::PlanSpec {
            start_mm: 10.0,
            end_mm: 390.0,
            targets: 5,
            runs: 2,
            ..Default::default()
        },
        dialect: None,
        notes: None,
    };
    let refused = rig
        .request(run_start())
        .await
        .expect_err("no alignment yet")
        .to_string();
    assert!(
        refused.contains("axis X has no beam alignment") && refused.contains("5.0 to 395.0 mm"),
        "{refused}"
    );
    let mut failed_once = false;
    for round in 1..=6 {
        rig.request(Request::AlignClear).await.expect("clear");
        for at in [span.0, span.1] {
            rig.twin.move_and_wait(at).await;
            tokio::time::sleep(Duration::from_millis(1500)).await;
            let spot2 = rig
                .snapshot()
                .await
                .psd
                .is_some_and(|p| p.spots_um[1].is_some());
            if !spot2 {
                // PSD2 lost its spot on the way: bring the follower to the carriage.
                rig.request(Request::Follower {
                    action: FollowerAction::Move,
                    mm: Some(at),
                })
                .await
                .expect("follower");
                tokio::time::sleep(Duration::from_millis(1500)).await;
            }
            let st = rig
                .request(Request::AlignRead { at_mm: Some(at) })
                .await
                .expect("read");
            let targets = rig.twin.plant.target_readings(axiscomp::util::clock::now());
            for k in 0..3 {
                if st["spots"][k].is_null()
                    && let Some(t) = targets[k]
                {
                    rig.request(Request::AlignTarget {
                        psd: k + 1,
                        x: t.x,
                        y: t.y,
                    })
                    .await
                    .expect("target");
                }
            }
        }
        let adv = rig
            .request(Request::AlignAdvice {
                from_mm: span.0,
                to_mm: span.1,
                axis: Some("X".into()),
            })
            .await
            .expect("advice");
        if adv["passed"].as_bool() == Some(true) {
            let m = rig.twin.plant.mount();
            assert!(round > 1, "mounted well enough already: {before:?}");
            let got = adv["misalignment_urad"][0].as_f64().expect("yaw");
            assert!(
                (got.abs() - m.yaw.abs() * 1e6).abs() < 80.0,
                "reported yaw {got:.0} µrad, truth {:.0} µrad",
                m.yaw * 1e6
            );
            assert!(m.yaw.abs() < 1e-3 && m.pitch.abs() < 1e-3, "{m:?}");
            assert!(failed_once, "the first round's check failed");
            // The passed alignment is stored for axis X: a run over its span starts.
            let started = rig
                .request(run_start())
                .await
                .expect("aligned: the run starts");
            assert!(started["run_id"].as_i64().is_some(), "{started}");
            rig.request(Request::RunAbort).await.expect("abort");
            return;
        }
        if !failed_once {
            // The stored failed check refuses a run, saying which PSD leaves and what to turn.
            failed_once = true;
            let refused = rig
                .request(run_start())
                .await
                .expect_err("not aligned")
                .to_string();
            assert!(
                refused.contains("did not pass")
                    && refused.contains("PSD")
                    && refused.contains("turn"),
                "{refused}"
            );
        }
        let turns = adv["turns"].as_array().expect("turns").clone();
        assert!(!turns.is_empty(), "not passed and nothing to turn: {adv}");
        for t in turns {
            let screw = Screw::parse(t["screw"].as_str().expect("screw")).expect("a screw");
            rig.twin
                .plant
                .turn_screw(screw, t["turns"].as_f64().expect("turns"));
        }
    }
    panic!(
        "not aligned in 6 rounds: mount {:?}",
        rig.twin.plant.mount()
    );
}

/// The live service, the beam cut mid-run (all three PSDs dark, as when someone walks through
/// the beam): the run pauses and says why in the snapshot, the twin's CNC stops at its next
/// stop, nothing is captured while the beam is off, and once it is back the rest of the cycle
/// runs and the run finishes with every capture stored exactly once.
#[tokio::test(start_paused = true)]
async fn the_service_pauses_a_run_while_the_beam_is_cut_and_finishes_it_with_every_capture_once() {
    use crate::helpers::{RigOptions, ServiceRig, align_service, short_plan};
    use axiscomp::service::api::Request;
    use axiscomp::store::{RunId, Store};

    let rig = ServiceRig::start(RigOptions {
        service_toml: "[tracking]\nrest_ms = 200\naverage_frames = 100\nsettle_ms = 100\n\n\
                       [capture]\nframes = 100\nsettle_ms = 200\n"
            .into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    let plan = short_plan();
    let travel = Plan::new(plan.clone()).expect("plan").travel_mm();
    align_service(&rig.socket, &rig.twin, travel).await;
    let started = rig
        .request(Request::RunStart {
            plan: plan.clone(),
            dialect: None,
            notes: None,
        })
        .await
        .expect("aligned: the run starts");
    let id = RunId(started["run_id"].as_i64().expect("run id"));
    let captures = || async {
        rig.request(Request::RunStatus).await.expect("run status")["captures"]
            .as_u64()
            .unwrap_or(0)
    };
    let t0 = axiscomp::util::clock::now();
    while captures().await < 4 {
        assert!(
            axiscomp::util::clock::since(t0) < Duration::from_secs(90),
            "no 4 captures in 90 s"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    for k in 0..3 {
        rig.twin.plant.set_blocked(k, true);
    }
    rig.wait_for(10, "the run paused", |s| {
        s.run.as_ref().is_some_and(|r| r.paused.is_some())
    })
    .await;
    let why = rig
        .snapshot()
        .await
        .run
        .and_then(|r| r.paused)
        .unwrap_or_default();
    assert!(why.contains("PSD1, PSD2, PSD3 have no spot"), "{why}");
    let t1 = axiscomp::util::clock::now();
    while !rig.twin.cnc.lock().map(|c| c.stopped).unwrap_or(false) {
        assert!(
            axiscomp::util::clock::since(t1) < Duration::from_secs(30),
            "the twin's CNC did not stop"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let at_stop = captures().await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    assert_eq!(captures().await, at_stop, "captured with the beam off");
    for k in 0..3 {
        rig.twin.plant.set_blocked(k, false);
    }
    let t2 = axiscomp::util::clock::now();
    loop {
        let st = rig.request(Request::RunStatus).await.expect("run status");
        match st["state"].as_str() {
            Some("running") => {}
            Some("finished") => break,
            _ => panic!("the run ended so: {st}"),
        }
        assert!(
            axiscomp::util::clock::since(t2) < Duration::from_secs(240),
            "not finished: {st}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let stored = Store::open_read_only(&rig.store)
        .expect("store")
        .captures(id)
        .expect("captures");
    let keys: BTreeSet<TargetKey> = stored.iter().map(TargetKey::of).collect();
    let p = Plan::new(plan).expect("plan");
    assert_eq!(
        stored.len(),
        p.capture_count(),
        "every capture exactly once"
    );
    assert_eq!(keys.len(), p.capture_count(), "no capture twice");
}
