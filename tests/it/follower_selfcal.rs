//! The stop-and-go self-calibration's procedure (`follower::selfcal`), with literal values:
//! the plan of stops, the dwell, the collection of handover records (arming on the lead-in,
//! kept and skipped steps, progress, time left), the stored form of a map with its
//! certificate, and a certificate joining a self-calibrated map.

use axiscomp::follower::selfcal::{Collector, LEAD_IN_MM, Plan, Spec, Taken, Timing, long_degree};
use axiscomp::follower::{self, Certificate, MapSettings, Source};
use axiscomp::track::{HandoverKind, HandoverRecord, Strategy, TrackSettings};
use std::time::Duration;

fn spec() -> Spec {
    Spec {
        from_mm: 0.0,
        to_mm: 20.0,
        step_mm: 3.75,
        passes: 2,
        probe_every: 2,
    }
}

fn timing() -> Timing {
    Timing {
        frame_rate_hz: 500.0,
        average_frames: 200,
        rest: Duration::from_millis(300),
        settle: Duration::from_millis(100),
        follower_velocity_mm_s: 200.0,
        follower_accel_mm_s2: 5000.0,
        sync: Duration::from_millis(10),
        feed_mm_min: 3000.0,
        accel_mm_s2: 500.0,
    }
}

/// A handover record of the follower from `from` to `to` (mm), optical or by the encoder.
fn record(kind: HandoverKind, from: f64, to: f64) -> HandoverRecord {
    HandoverRecord {
        unix_us: 0,
        kind,
        before: [to - from, 0.001],
        after: [0.0, 0.0],
        n_before: 200,
        n_after: 200,
        frame_sd: [1e-3, 1e-3],
        encoder_before: from,
        encoder_after: to,
        delta: [to - from + 0.0002, 0.0004],
        variance: [1e-8, 1e-8],
    }
}

#[test]
fn the_plan_steps_over_the_span_in_passes_with_probes() {
    let plan = Plan::new(spec()).expect("plan");
    // Five steps a pass (20 / 3.75); a probe back and forth after every second stop but the
    // last; the second pass down.
    let want = [
        3.75, 7.5, 3.75, 7.5, 11.25, 15.0, 11.25, 15.0, 18.75, // up
        15.0, 11.25, 15.0, 11.25, 7.5, 3.75, 7.5, 3.75, 0.0, // down
    ];
    assert_eq!(plan.stops(), &want);
    assert_eq!(plan.approach(), [12.0, 0.0]);
    assert_eq!(plan.positions().len(), 20);
    assert_eq!(plan.positions()[..3], [12.0, 0.0, 3.75]);
    // One pass, no probes: the stops up the span only.
    let one = Plan::new(Spec {
        passes: 1,
        probe_every: 0,
        ..spec()
    })
    .unwrap();
    assert_eq!(one.stops(), &[3.75, 7.5, 11.25, 15.0, 18.75]);
}

#[test]
fn plans_that_cannot_run_are_refused_with_the_reason() {
    for (s, what) in [
        (
            Spec {
                step_mm: 4.5,
                ..spec()
            },
            "a step of 4.5 mm over 0 to 20 mm: give a step above 0.5 and up to 4 mm",
        ),
        (
            Spec {
                to_mm: 10.0,
                ..spec()
            },
            "a span of 10.0 mm (0 to 10 mm): give at least 12 mm",
        ),
        (
            Spec {
                passes: 0,
                ..spec()
            },
            "0 passes: give at least one",
        ),
        (
            Spec {
                to_mm: f64::NAN,
                ..spec()
            },
            "give finite numbers",
        ),
    ] {
        let e = Plan::new(s).unwrap_err().to_string();
        assert!(e.starts_with("self-calibration: "), "{e}");
        assert!(e.contains(what), "{e}");
    }
    // Enough stops for the fit: 18 stops cannot carry degree 12 (21 needed), degree 2 can.
    let plan = Plan::new(spec()).unwrap();
    let e = plan.check_fit(&MapSettings::default()).unwrap_err();
    assert!(
        e.to_string()
            .contains("18 stops (0.0 to 20.0 mm by 3.75 mm, 2 passes) are too few for the fit: it needs at least 21"),
        "{e}"
    );
    plan.check_fit(&MapSettings {
        long_degree: 2,
        ..MapSettings::default()
    })
    .expect("degree 2");
    assert_eq!(
        (long_degree(60.0), long_degree(120.0), long_degree(1000.0)),
        (2, 2, 12)
    );
    assert_eq!(long_degree(400.0), 5);
}

#[test]
fn the_dwell_covers_rest_averaging_and_the_followers_step() {
    let t = timing();
    // 0.3 s rest + 2 × 200 frames at 500 Hz (0.8 s) + the follower's 3.75 mm step (a
    // triangular profile at 5000 mm/s², 2·√(3.75/5000) = 0.0548 s, plus two 10 ms SYNCs) +
    // 0.1 s settle = 1.2748 s; × 1.25 + 0.5 s = 2.093 s, up to 2.1 s.
    assert_eq!(t.dwell_s(3.75), 2.1);
    let words = t.dwell_text(3.75);
    assert!(
        words.starts_with("dwell 2.1 s at each stop: rest detection 0.30 s + 200 frames before at 500 Hz (0.40 s) + the follower's 3.75 mm step 0.07 s"),
        "{words}"
    );
    // 1000 frames a side at 500 Hz: 4 s of averaging.
    let slow = Timing {
        average_frames: 1000,
        ..t
    };
    assert_eq!(slow.dwell_s(3.75), 6.1);
    // The carriage: 3.75 mm at 50 mm/s and 500 mm/s² is triangular (2·√(3.75/500)).
    assert!((t.carriage_move_s(3.75) - 2.0 * (3.75f64 / 500.0).sqrt()).abs() < 1e-12);
    // The whole plan: the lead-in (12 mm), back to the start, then 18 stops, each a move and
    // a dwell.
    let plan = Plan::new(spec()).unwrap();
    let moves: f64 = [12.0, 12.0]
        .iter()
        .chain(&[3.75; 18])
        .map(|&d| t.carriage_move_s(d) + 2.1)
        .sum();
    assert!((plan.machine_time_s(&t) - moves).abs() < 1e-9);
}

#[test]
fn the_collector_arms_on_the_lead_in_and_keeps_optical_steps() {
    let plan = Plan::new(spec()).unwrap();
    let t0 = axiscomp::util::clock::now();
    let mut c = Collector::new(plan, t0);
    let base = TrackSettings {
        strategy: Strategy::Encoder,
        ..TrackSettings::default()
    };
    // Before the start: the service's own settings, with the overlap strategy (an encoder
    // strategy records no handovers).
    assert_eq!(
        c.tracking(&base, 300),
        TrackSettings {
            strategy: Strategy::Overlap,
            ..base
        }
    );
    assert_eq!(c.progress().stops_planned, 18);
    let time = timing();
    let whole = c.left_s(&time);
    // The approach from far below: followed by the encoder, then a small overlap step.
    assert_eq!(
        c.handle_record(&record(HandoverKind::Encoder, 100.0, 140.2)),
        Taken::Approach
    );
    assert_eq!(
        c.handle_record(&record(HandoverKind::Overlap, 140.2, 142.0)),
        Taken::Approach
    );
    // The lead-in's last leg: −12 mm within the follow band.
    assert_eq!(
        c.handle_record(&record(HandoverKind::Encoder, 142.0, 130.2)),
        Taken::Armed
    );
    let p = c.progress();
    assert!(p.armed && p.stops_seen == 0 && p.approach_records == 2);
    // From the start: the procedure's settings.
    let s = c.tracking(&base, 300);
    assert_eq!(s.strategy, Strategy::Overlap);
    assert_eq!(s.average_frames, 300);
    assert_eq!((s.edge_mm, s.handover_mm), (3.75 + 0.45, 1.5));
    // Stop 1 optical, stop 2 by the encoder (skipped), stop 3 optical (the probe back down).
    assert_eq!(
        c.handle_record(&record(HandoverKind::Overlap, 130.2, 133.95)),
        Taken::Kept
    );
    assert_eq!(
        c.handle_record(&record(HandoverKind::Encoder, 133.95, 137.7)),
        Taken::Skipped
    );
    assert_eq!(
        c.handle_record(&record(HandoverKind::Overlap, 137.7, 133.94)),
        Taken::Kept
    );
    // A step to the same encoder position measures nothing: skipped too.
    assert_eq!(
        c.handle_record(&record(HandoverKind::Overlap, 133.94, 133.94)),
        Taken::Skipped
    );
    let p = c.progress();
    assert_eq!(
        (p.stops_seen, p.steps_kept, p.skipped, p.out_of_plan),
        (4, 2, 2, 0)
    );
    let steps = c.steps();
    assert_eq!(steps.len(), 2);
    assert_eq!((steps[0].from_mm, steps[0].to_mm), (130.2, 133.95));
    assert!((steps[1].along_mm - (133.94 - 137.7 + 0.0002)).abs() < 1e-12);
    assert_eq!(steps[1].vertical_mm, 0.0004);
    assert_eq!(steps[1].variance, [1e-8, 1e-8]);
    // A lead-in's record once stops have been counted is a stop like any other.
    assert_eq!(
        c.handle_record(&record(HandoverKind::Encoder, 133.94, 121.94)),
        Taken::Skipped
    );
    // A kept step the plan did not ask for (stop 6 is a +3.75 mm move) is counted as such.
    assert_eq!(
        c.handle_record(&record(HandoverKind::Overlap, 121.94, 131.0)),
        Taken::Kept
    );
    assert_eq!(c.progress().out_of_plan, 1);
    // Time left: the 12 stops not seen, each a move and a dwell.
    let left: f64 = [3.75; 12]
        .iter()
        .map(|&d| time.carriage_move_s(d) + 2.1)
        .sum();
    assert!((c.left_s(&time) - left).abs() < 1e-9, "{}", c.left_s(&time));
    assert!(whole > left);
    assert!(!c.all_seen());
    for _ in 0..12 {
        c.handle_record(&record(HandoverKind::Overlap, 131.0, 134.75));
    }
    assert!(c.all_seen());
    assert_eq!(c.left_s(&time), 0.0);
    assert_eq!(
        c.elapsed(t0 + Duration::from_secs(90)),
        Duration::from_secs(90)
    );
}

#[test]
fn an_approach_from_further_up_arms_again_before_the_first_stop() {
    let mut c = Collector::new(Plan::new(spec()).unwrap(), axiscomp::util::clock::now());
    // The carriage was 24 mm above the start: the first leg is −12 mm too.
    assert_eq!(
        c.handle_record(&record(HandoverKind::Encoder, 24.0, 12.1)),
        Taken::Armed
    );
    assert_eq!(
        c.handle_record(&record(HandoverKind::Encoder, 12.1, 0.05)),
        Taken::Armed
    );
    assert_eq!(
        c.handle_record(&record(HandoverKind::Overlap, 0.05, 3.8)),
        Taken::Kept
    );
    let p = c.progress();
    assert_eq!((p.stops_seen, p.steps_kept, p.out_of_plan), (1, 1, 0));
    const { assert!(LEAD_IN_MM > 4.5, "beyond PSD2's half-width") };
}

/// A certificate joins a self-calibrated map: the long shape from the certificate, the
/// self-calibration's terms kept; the stored form keeps the certificate's points and reads
/// back, and a map stored without them reads as before.
#[test]
fn a_certificate_joins_a_self_calibration_and_is_stored_with_the_map() {
    // Steps of a follower with a 1 µm screw term and a 0.5 µm vertical bump, over 40 mm both
    // ways, noiseless.
    let v = |x: f64| 0.5e-3 * (std::f64::consts::PI * x / 40.0).sin();
    let a = |x: f64| 1e-3 * (2.0 * std::f64::consts::PI * x / 5.0).sin();
    let mut xs: Vec<f64> = (0..=10).map(|k| k as f64 * 3.75).collect();
    let back: Vec<f64> = xs.iter().rev().skip(1).copied().collect();
    xs.extend(back);
    let steps: Vec<follower::Step> = xs
        .windows(2)
        .map(|w| follower::Step {
            from_mm: w[0],
            to_mm: w[1],
            along_mm: (w[1] + a(w[1])) - (w[0] + a(w[0])),
            vertical_mm: v(w[1]) - v(w[0]),
            variance: [1e-8, 1e-8],
        })
        .collect();
    let settings = MapSettings {
        long_degree: 2,
        ..MapSettings::default()
    };
    let own = follower::build(&steps, None, &settings).expect("self-calibration only");
    assert_eq!(own.sources.long, Source::None);
    let cert = Certificate::parse(
        "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n20,1.0,+,0.2\n40,2.0,+,0.2\n",
        "stage.csv",
    )
    .unwrap();
    let joined = own.with_certificate(&cert);
    let built = follower::build(&steps, Some(&cert), &settings).unwrap();
    assert_eq!(joined, built, "the same as building with both");
    assert_eq!(joined.sources.long, Source::Certificate);
    assert_eq!(joined.vertical_mm, own.vertical_mm);
    let text = follower::stored_toml(&joined, Some(&cert));
    let (map, c) = follower::from_stored_toml(&text, "map 1").expect("reads back");
    assert_eq!((map, c), (joined.clone(), Some(cert)));
    // The plain TOML reader ignores the certificate's table.
    assert_eq!(
        follower::FollowerMap::from_toml(&text, "map 1").unwrap(),
        joined
    );
    let (old, none) = follower::from_stored_toml(&own.to_toml(), "map 2").unwrap();
    assert_eq!((old, none), (own, None));
}
