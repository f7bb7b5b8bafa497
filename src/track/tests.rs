//! The tracker against a virtual plant: stitching, follower moves and their problems.

use super::*;
use crate::optics::Spot;
use crate::sim::Rng;

/// A virtual plant: carriage at `carriage` (mm), follower encoder `enc`, the follower's own
/// errors along (`fu`) and across (`fv`), PSD noise 1 µm.
struct Bench {
    t0: Instant,
    now: Instant,
    carriage: f64,
    enc: f64,
    target: Option<f64>,
    rng: Rng,
    seq: u64,
    /// Every absolute move commanded (mm).
    moves: Vec<f64>,
    /// The drive is enabled (it moves and says so) / it stands still whatever it is told.
    ready: bool,
    stalled: bool,
    /// PSD2's half-size (mm): no spot beyond it.
    half_mm: f64,
    /// The follower's own error along is `along · fu`.
    along: f64,
}

fn fu(d: f64) -> f64 {
    3e-3 * (d / 10.0).sin()
}
fn fv(d: f64) -> f64 {
    2e-3 * (d / 7.0 + 0.3).sin()
}

impl Bench {
    fn new() -> Self {
        let t0 = crate::util::clock::now();
        Bench {
            t0,
            now: t0,
            carriage: 0.0,
            enc: 0.0,
            target: None,
            rng: Rng::new(3),
            seq: 0,
            moves: Vec::new(),
            ready: true,
            stalled: false,
            half_mm: f64::INFINITY,
            along: 1.0,
        }
    }

    fn frame(&mut self) -> Frame {
        let noise = 1e-3;
        let x = self.carriage - (self.enc + self.along * fu(self.enc)) + self.rng.gauss(noise);
        let y = -fv(self.enc) + self.rng.gauss(noise);
        self.seq += 1;
        let other = Some(Spot { x: 0.0, y: 0.0 });
        Frame {
            seq: self.seq,
            at: self.now,
            unix_us: (self.now - self.t0).as_micros() as i64,
            spots: [
                other,
                (x.abs() <= self.half_mm).then_some(Spot { x, y }),
                other,
            ],
            sums: [5.0; 3],
        }
    }

    /// Advance 2 ms: one frame; the follower runs at 100 mm/s towards its target.
    fn step(&mut self, tr: &mut Tracker) {
        self.now += Duration::from_millis(2);
        if let Some(t) = self.target.filter(|_| self.ready && !self.stalled) {
            let max = 100.0 * 0.002;
            let d = (t - self.enc).clamp(-max, max);
            self.enc += d;
            if (t - self.enc).abs() < 1e-12 {
                self.enc = t;
                self.target = None;
            }
        }
        let f = self.frame();
        tr.handle_frame(&f, self.now);
        while let Some(c) = tr.poll_command() {
            self.target = Some(match c {
                FollowerCommand::MoveTo(t) => {
                    self.moves.push(t);
                    t
                }
                FollowerCommand::Follow { target_mm, .. } => target_mm,
            });
        }
        tr.handle_follower(
            FollowerState {
                position_mm: self.enc,
                ready: self.ready,
                target_reached: self.target.is_none(),
                at: None,
            },
            self.now,
        );
    }

    fn run(&mut self, tr: &mut Tracker, ms: u64) {
        for _ in 0..ms / 2 {
            self.step(tr);
        }
    }
}

fn referenced(strategy: Strategy) -> (Bench, Tracker) {
    let mut b = Bench::new();
    let mut tr = Tracker::new(TrackSettings {
        strategy,
        ..TrackSettings::default()
    });
    b.run(&mut tr, 50);
    assert!(tr.reference());
    (b, tr)
}

/// The follower events of `tr` since the last call: problems by their text, recoveries.
fn follower_events(tr: &mut Tracker) -> Vec<String> {
    std::iter::from_fn(|| tr.poll_event())
        .filter_map(|e| match e {
            TrackEvent::FollowerProblem(p) => Some(p),
            TrackEvent::FollowerRecovered => Some("recovered".into()),
            _ => None,
        })
        .collect()
}

/// The handover records `tr` gave since the last call (other events are dropped).
fn handovers(tr: &mut Tracker) -> Vec<HandoverRecord> {
    std::iter::from_fn(|| tr.poll_event())
        .filter_map(|e| match e {
            TrackEvent::Handover(r) => Some(r),
            _ => None,
        })
        .collect()
}

/// Move the carriage by `by` mm at 10 mm/s (a jog: slow enough for the tracker to hand over
/// at rest after it, not to follow it).
fn jog(b: &mut Bench, tr: &mut Tracker, by: f64) {
    let steps = (by.abs() / 0.02).ceil().max(1.0) as usize;
    for _ in 0..steps {
        b.carriage += by / steps as f64;
        b.step(tr);
    }
}

/// Jog the carriage 1 mm at a time until the tracker starts a follower move.
fn until_a_move(b: &mut Bench, tr: &mut Tracker) {
    let moves = b.moves.len();
    while b.moves.len() == moves {
        jog(b, tr, 1.0);
        if b.moves.len() > moves {
            return;
        }
        for _ in 0..750 {
            b.step(tr);
            if b.moves.len() > moves {
                return;
            }
        }
        assert!(b.carriage < 50.0, "no follower move by {} mm", b.carriage);
    }
}

#[test]
fn a_follower_problem_is_said_once_and_its_end_is_said_when_the_follower_serves_again() {
    // Not ready in the middle of a move: said; ready again: recovered.
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    follower_events(&mut tr);
    until_a_move(&mut b, &mut tr);
    b.ready = false;
    b.run(&mut tr, 20);
    assert_eq!(follower_events(&mut tr), ["the follower is not ready"]);
    b.run(&mut tr, 500);
    b.ready = true;
    b.run(&mut tr, 20);
    assert_eq!(follower_events(&mut tr), ["recovered"]);

    // A move that does not end in time: said once; the next move that does: recovered.
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    until_a_move(&mut b, &mut tr);
    b.stalled = true;
    b.run(&mut tr, 10_500);
    let target = b.moves.last().copied().unwrap_or_default();
    assert_eq!(
        follower_events(&mut tr),
        [format!(
            "the follower did not reach {target:.3} mm in 10.0 s"
        )]
    );
    b.stalled = false;
    b.run(&mut tr, 1000);
    assert_eq!(follower_events(&mut tr), Vec::<String>::new());
    until_a_move(&mut b, &mut tr);
    b.run(&mut tr, 1000);
    assert_eq!(follower_events(&mut tr), ["recovered"]);
}

#[test]
fn overlap_stitch_measures_the_followers_true_displacement() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    let (u0, v0) = (fu(b.enc), fv(b.enc));
    // Jog the carriage 1 mm at a time to 40 mm, resting 1.5 s at each step.
    for _ in 1..=40 {
        jog(&mut b, &mut tr, 1.0);
        b.run(&mut tr, 1500);
    }
    let s = tr.stitch();
    assert!(s.valid);
    assert!(s.handovers >= 15, "{} handovers", s.handovers);
    let records = handovers(&mut tr);
    assert!(records.iter().all(|r| r.kind == HandoverKind::Overlap));
    assert_eq!(records.len(), s.handovers);
    // Truth: PSD2 is at enc + fu(enc) along, fv(enc) across, relative to the reference.
    let true_u = b.enc + fu(b.enc) - u0;
    let true_v = fv(b.enc) - v0;
    let (sd_u, sd_v) = (s.variance[0].sqrt(), s.variance[1].sqrt());
    assert!(sd_u > 0.0 && sd_u < 1e-3, "{sd_u}");
    assert!(
        (s.follower_mm - true_u).abs() < 4.0 * sd_u,
        "{} vs {true_u} (sd {sd_u})",
        s.follower_mm
    );
    assert!(
        (s.vertical_mm - true_v).abs() < 4.0 * sd_v,
        "{} vs {true_v} (sd {sd_v})",
        s.vertical_mm
    );
    // The encoder alone would be off by the follower's own error.
    assert!((fu(b.enc) - u0).abs() > 1e-3);
    assert!((b.enc - true_u).abs() > 3.0 * sd_u, "sd {sd_u}");
    // Offline re-stitching of the records gives the same.
    let re = restitch(&records, true, tr.settings());
    assert!((re.follower_mm - s.follower_mm).abs() < 1e-9);
    assert!((re.vertical_mm - s.vertical_mm).abs() < 1e-12);
    let enc = restitch(&records, false, tr.settings());
    assert!((enc.follower_mm - b.enc).abs() < 1e-9);
}

/// A follower whose own error differs from its encoder by tens of µm over a step (90 µm
/// along here, 9 µm/mm at its steepest) is measured by every overlap handover, not taken
/// for a carriage that moved: the self-calibration maps the follower by these differences.
#[test]
fn a_followers_own_error_is_measured_not_bridged() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    b.along = 30.0;
    let u0 = b.along * fu(b.enc);
    for _ in 1..=40 {
        jog(&mut b, &mut tr, 1.0);
        b.run(&mut tr, 1500);
    }
    let kinds: Vec<HandoverKind> = handovers(&mut tr).iter().map(|r| r.kind).collect();
    assert!(kinds.len() >= 15, "{} handovers", kinds.len());
    assert!(
        kinds.iter().all(|k| *k == HandoverKind::Overlap),
        "{kinds:?}"
    );
    let s = tr.stitch();
    let true_u = b.enc + b.along * fu(b.enc) - u0;
    assert!(
        (s.follower_mm - true_u).abs() < 0.002,
        "the stitch at {:.4} mm, the follower at {true_u:.4} mm",
        s.follower_mm
    );
}

/// The carriage rests 2 mm down (a program's overrun point), the tracker hands over there,
/// and the carriage goes on to its target while the follower steps: it stands in both
/// windows, and PSD2's difference is the follower's step plus the carriage's 2 mm. The
/// encoder tells, and bridges the step.
#[test]
fn a_carriage_that_moved_during_a_handover_is_bridged_by_the_encoder() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    let u0 = fu(b.enc);
    jog(&mut b, &mut tr, -2.0);
    let moves = b.moves.len();
    for _ in 0..1500 {
        b.step(&mut tr);
        if b.moves.len() > moves {
            break;
        }
    }
    assert!(b.moves.len() > moves, "no handover at the overrun point");
    // Back to the target at 50 mm/s while the follower steps.
    for _ in 0..20 {
        b.carriage += 0.1;
        b.step(&mut tr);
    }
    b.run(&mut tr, 1500);
    let records = handovers(&mut tr);
    assert!(
        records.iter().any(|r| r.kind == HandoverKind::Encoder),
        "the step is an encoder step"
    );
    assert!(records.iter().all(|r| r.kind == HandoverKind::Encoder));
    let s = tr.stitch();
    let true_u = b.enc + fu(b.enc) - u0;
    assert!(
        (s.follower_mm - true_u).abs() < 0.01,
        "the stitch at {:.4} mm, the follower at {true_u:.4} mm",
        s.follower_mm
    );
}

#[test]
fn overlap_follows_by_encoder_when_the_carriage_does_not_stop() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    // Move continuously at 5 mm/s for 4 s.
    for _ in 0..2000 {
        b.carriage += 5.0 * 0.002;
        b.step(&mut tr);
    }
    b.run(&mut tr, 2000);
    let mut kinds = Vec::new();
    let mut followed = false;
    while let Some(e) = tr.poll_event() {
        match e {
            TrackEvent::Handover(r) => kinds.push(r.kind),
            TrackEvent::FollowedWhileMoving { .. } => followed = true,
            _ => {}
        }
    }
    assert!(followed);
    assert!(kinds.contains(&HandoverKind::Encoder), "{kinds:?}");
    let s = tr.stitch();
    // The spot never left the PSD.
    assert!(s.valid);
    // Encoder steps carry the encoder's uncertainty.
    assert!(s.variance[0].sqrt() >= tr.settings().encoder_sd_mm);
}

/// A run moves the carriage target to target, back and forth, and the follower follows each
/// move by its encoder: the steps' errors telescope (the stage's error where the chain ends
/// less where it began), so the stitch's variance is that of one bridge over the net
/// distance, not a sum that grows with every move (issue 24: 1.4 → 12.8 µm through a run
/// whose captures agreed within 0.3 µm), and the stitch is still true within it.
#[test]
fn encoder_steps_back_and_forth_state_the_uncertainty_of_one_bridge() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    let before = tr.stitch().follower_mm;
    let mut steps = 0;
    for pass in 0..6 {
        for _ in 0..4 {
            let by = if pass % 2 == 0 { 25.0 } else { -25.0 };
            for _ in 0..1250 {
                b.carriage += by / 1250.0;
                b.step(&mut tr);
            }
            b.run(&mut tr, 2500);
            steps += std::iter::from_fn(|| tr.poll_event())
                .filter(|e| matches!(e, TrackEvent::Handover(r) if r.kind == HandoverKind::Encoder))
                .count();
        }
    }
    assert!(steps >= 20, "{steps} encoder steps");
    // Back where it began: one bridge of the net distance (about zero), not 24 of 25 mm.
    let st = tr.stitch();
    assert!(st.valid);
    let s = tr.settings();
    let one = s.encoder_sd_mm + s.encoder_sd_per_mm * b.enc.abs();
    let each = s.encoder_sd_mm + s.encoder_sd_per_mm * 25.0;
    assert!(
        (st.variance[0].sqrt() - one).abs() < 1e-9,
        "u {:.2} µm, one bridge {:.2} µm, {steps} steps summed {:.2} µm",
        st.variance[0].sqrt() * 1e3,
        one * 1e3,
        (steps as f64).sqrt() * each * 1e3
    );
    // True within its U: PSD2 stands at enc + fu(enc); the stitch says follower_mm.
    let err = (st.follower_mm - before) - (b.enc + fu(b.enc) - fu(0.0));
    assert!(
        err.abs() <= 2.0 * st.variance[0].sqrt(),
        "off by {:.2} µm",
        err * 1e3
    );
}

/// The carriage runs 20 mm down and stops: the follower follows it by its encoder, then
/// ends with its approach from below (20 µm down, then up to where it stood), so the
/// tracker knows the stage stands in its "up" state whatever its samples showed on the way
/// down; the step is taken from the encoder once the approach is over. Without an
/// approach configured, the follower stays where following left it.
#[test]
fn following_ends_with_an_approach_from_below() {
    for approach in [0.02, 0.0] {
        let (mut b, mut tr) = referenced(Strategy::Overlap);
        let mut s = *tr.settings();
        s.approach_mm = approach;
        tr.set_settings(s);
        for _ in 0..2000 {
            b.carriage -= 10.0 * 0.002;
            b.step(&mut tr);
        }
        assert_eq!(tr.motion(), Direction::Down);
        b.run(&mut tr, 3000);
        let mut records = Vec::new();
        while let Some(e) = tr.poll_event() {
            if let TrackEvent::Handover(r) = e {
                records.push(r);
            }
        }
        let last = records.last().expect("a handover");
        assert_eq!(last.kind, HandoverKind::Encoder);
        assert!(!tr.handing_over());
        if approach > 0.0 {
            // The last two moves: the approach point 20 µm below, then the target, where
            // the encoder step ends.
            let n = b.moves.len();
            assert!(n >= 2, "{:?}", b.moves);
            let (via, target) = (b.moves[n - 2], b.moves[n - 1]);
            assert!((target - via - 0.02).abs() < 1e-9, "{via} then {target}");
            assert_eq!(last.encoder_after, target);
            assert_eq!(b.enc, target);
            assert_eq!(tr.motion(), Direction::Up);
        } else {
            // No move beyond following (whose last targets may step back: the state is then
            // whatever the samples say).
            assert!(b.moves.is_empty(), "{:?}", b.moves);
        }
        // PSD2 is where the carriage put the spot, within the encoder step's uncertainty.
        let st = tr.stitch();
        let spot = b.carriage - (b.enc + fu(b.enc));
        let psd2 = st.follower_mm + fu(0.0);
        assert!(
            (psd2 + spot - b.carriage).abs() < 5.0 * st.variance[0].sqrt(),
            "{psd2} + {spot} against {}",
            b.carriage
        );
    }
}

#[test]
fn encoder_strategy_follows_continuously() {
    let (mut b, mut tr) = referenced(Strategy::Encoder);
    for _ in 0..2000 {
        b.carriage += 10.0 * 0.002;
        b.step(&mut tr);
    }
    b.run(&mut tr, 500);
    let s = tr.stitch();
    assert_eq!(s.follower_mm, b.enc);
    assert!((b.carriage - b.enc).abs() < 0.5, "spot kept near centre");
    assert!(s.handovers > 10);
    let sd = s.variance[0].sqrt();
    let expect = 1e-3 + 5e-6 * b.enc.abs();
    assert!((sd - expect).abs() < 1e-12, "{sd}");
    let sd_v = s.variance[1].sqrt();
    assert!(
        (sd_v - (0.2e-3 + 3e-6 * b.enc.abs())).abs() < 1e-12,
        "{sd_v}"
    );
}

/// Whoever puts a map in use gets the same map back, as its own type; asked for another
/// type, the tracker has none.
#[test]
fn the_map_in_use_comes_back_as_it_was_given() {
    #[derive(Debug)]
    struct Flat;
    impl StageCorrection for Flat {
        fn correction(&self, _: f64, _: Direction) -> [f64; 2] {
            [0.0; 2]
        }
        fn difference_variance(&self, _: f64, _: f64, _: Direction, _: Direction) -> [f64; 2] {
            [0.0; 2]
        }
    }
    let mut tr = Tracker::new(TrackSettings::default());
    assert!(tr.map::<Flat>().is_none());
    let flat = Arc::new(Flat);
    tr.set_map(Some(flat.clone()));
    assert!(tr.map::<Flat>().is_some_and(|m| Arc::ptr_eq(m, &flat)));
    assert!(tr.map::<crate::follower::FollowerMap>().is_none());
    tr.set_map::<Flat>(None);
    assert!(tr.map::<Flat>().is_none());
}

/// A follower map of the bench's own errors (`fu`, `fv`) every 0.25 mm over 100 mm.
fn bench_map() -> crate::follower::FollowerMap {
    use crate::follower::{FollowerMap, Source, Sources};
    let xs: Vec<f64> = (0..=400).map(|k| k as f64 * 0.25).collect();
    let fus: Vec<f64> = xs.iter().map(|&x| fu(x)).collect();
    FollowerMap {
        sources: Sources {
            long: Source::Certificate,
            periodic: Source::None,
            reversal: Source::None,
            vertical: Source::SelfCalibration,
        },
        certificate_name: None,
        self_calibration: None,
        long_positions_mm: xs.clone(),
        long_up_mm: fus.clone(),
        long_down_mm: fus,
        long_u_mm: vec![0.1e-3; xs.len()],
        periodic: None,
        reversal: None,
        certificate_reversal_mm: None,
        vertical_positions_mm: xs.clone(),
        vertical_mm: xs.iter().map(|&x| fv(x)).collect(),
        vertical_u_mm: vec![0.2e-3; xs.len()],
        vertical_slope: 0.0,
        vertical_line: None,
        vertical_reference: None,
        reuse: None,
    }
}

/// With a map of the follower's own errors, the encoder strategy's stitch is where PSD2
/// really is (along and vertically, from the reference), not where the encoder says.
#[test]
fn encoder_strategy_applies_the_follower_map() {
    use crate::follower::FollowerMap;
    let (mut b, mut tr) = referenced(Strategy::Encoder);
    let map = Arc::new(bench_map());
    tr.set_map(Some(map.clone()));
    assert!(
        tr.map::<FollowerMap>()
            .is_some_and(|m| Arc::ptr_eq(m, &map))
    );
    assert!(tr.reference());
    let (u0, v0, e0) = (fu(b.enc), fv(b.enc), b.enc);
    for _ in 0..2000 {
        b.carriage += 10.0 * 0.002;
        b.step(&mut tr);
    }
    b.run(&mut tr, 500);
    let s = tr.stitch();
    let true_u = b.enc + fu(b.enc) - u0 + e0;
    let true_v = fv(b.enc) - v0;
    // Linear interpolation every 0.25 mm of 3 µm and 2 µm sines: within 2 nm.
    assert!(
        (s.follower_mm - true_u).abs() < 2e-6,
        "{} vs {true_u}",
        s.follower_mm
    );
    assert!(
        (s.vertical_mm - true_v).abs() < 2e-6,
        "{} vs {true_v}",
        s.vertical_mm
    );
    assert!(
        (fu(b.enc) - u0).abs() > 1e-3,
        "the encoder alone would be off"
    );
    // The map's uncertainty replaces the per-mm terms, and the stage's repeatability beyond
    // its map the encoder's own. The map's points (0.1 µm each, independent) enter by the
    // weights linear interpolation gives them at each end of the bridge.
    let sd = s.variance.map(f64::sqrt);
    let mapped = tr.settings().mapped_sd_mm;
    let points = |x: f64| {
        let t = (x / 0.25).fract();
        (1.0 - t).powi(2) + t * t
    };
    let want = (mapped * mapped + 0.01e-6 * (points(e0) + points(b.enc))).sqrt();
    assert!((sd[0] - want).abs() < 1e-9, "{sd:?} against {want:e}");
}

/// The follow target is the carriage, whatever the follower does and however late its
/// reports come: the follower swinging ±0.5 mm at 5 Hz (a loop gone wrong), sampled at
/// 10 ms SYNCs that come up to 30 ms late, reported up to 40 ms after that; the carriage at
/// 50 mm/s. Every target after the first 100 ms is within 0.15 mm of the carriage at its
/// time (what is left is the follower's curve between its samples, up to 40 ms apart),
/// with the carriage's velocity.
#[test]
fn follow_targets_are_the_carriage_whatever_the_follower_does() {
    let t0 = crate::util::clock::now();
    let mut rng = Rng::new(11);
    let mut tr = Tracker::new(TrackSettings {
        strategy: Strategy::Encoder,
        ..TrackSettings::default()
    });
    let carriage = |t: f64| 5.0 + 50.0 * t;
    let follower = |t: f64| 5.0 + 50.0 * t + 0.5 * (2.0 * std::f64::consts::PI * 5.0 * t).sin();
    let at = |t: f64| t0 + Duration::from_secs_f64(t);
    // SYNC times (some late), each with the time its report arrives.
    let mut reports = Vec::new();
    let mut sync = 0.0;
    while sync < 1.0 {
        sync += 0.010
            + if rng.uniform(0.0, 1.0) < 0.1 {
                rng.uniform(0.0, 0.03)
            } else {
                0.0
            };
        reports.push((sync, sync + rng.uniform(0.0, 0.04)));
    }
    reports.sort_by(|a, b| a.1.total_cmp(&b.1));
    let (mut next, mut targets) = (0, Vec::new());
    for k in 1..500 {
        let t = k as f64 * 0.002;
        while next < reports.len() && reports[next].1 <= t {
            let (s, _) = reports[next];
            tr.handle_follower(
                FollowerState {
                    position_mm: follower(s),
                    ready: true,
                    target_reached: false,
                    at: Some(at(s)),
                },
                at(t),
            );
            next += 1;
        }
        let x = carriage(t) - follower(t) + rng.gauss(1e-3);
        let spot = Some(crate::optics::Spot { x, y: 0.0 });
        let f = Frame {
            seq: k,
            at: at(t),
            unix_us: 0,
            spots: [spot, spot, spot],
            sums: [5.0; 3],
        };
        tr.handle_frame(&f, at(t));
        while let Some(c) = tr.poll_command() {
            if let FollowerCommand::Follow {
                target_mm,
                velocity_mm_s,
                at,
            } = c
            {
                targets.push(((at - t0).as_secs_f64(), target_mm, velocity_mm_s));
            }
        }
    }
    assert!(targets.len() > 40, "{} targets", targets.len());
    for &(t, target, v) in targets.iter().filter(|x| x.0 > 0.1) {
        assert!(
            (target - carriage(t)).abs() < 0.15,
            "at {t:.3} s: target {target:.4}, carriage {:.4}",
            carriage(t)
        );
        assert!((v - 50.0).abs() < 2.0, "at {t:.3} s: {v} mm/s");
    }
}

#[test]
fn blocked_beam_invalidates_the_stitch() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    for _ in 0..400 {
        b.now += Duration::from_millis(2);
        let mut f = b.frame();
        f.spots[1] = None;
        tr.handle_frame(&f, b.now);
    }
    assert!(!tr.stitch().valid);
    assert_eq!(tr.poll_event(), Some(TrackEvent::SpotLost));
    b.run(&mut tr, 20);
    assert_eq!(tr.poll_event(), Some(TrackEvent::SpotFound));
    assert!(!tr.stitch().valid, "still broken until re-referenced");
    assert!(tr.reference());
    assert!(tr.stitch().valid);
}

/// A carriage that went on while the follower could not follow (issue 24: a make-up pass
/// visits only the missing targets, and the follower stood where none of them was) is found
/// where it stands: the follower goes there by its final approach, the stitch is not bridged
/// while it moves, and once it stands PSD2's spot is found again, bridged by the encoder to
/// the carriage's true position.
#[test]
fn a_follower_that_lost_the_spot_goes_to_the_carriage() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    b.half_mm = 4.5;
    let before = tr.stitch().follower_mm;
    b.carriage = 150.0;
    b.run(&mut tr, 600);
    assert!(tr.is_lost(), "the spot is off PSD2");
    assert_eq!(tr.poll_event(), Some(TrackEvent::SpotLost));
    assert!(tr.seek(150.0, b.now));
    assert!(tr.seeking());
    assert!(!tr.seek(150.1, b.now), "already on its way there");
    let mut found = 0;
    let mut bridged = false;
    for _ in 0..2000 {
        b.step(&mut tr);
        while let Some(e) = tr.poll_event() {
            if e == TrackEvent::SpotFound {
                found += 1;
                // As the pipeline does on every SpotFound: refused while the follower moves.
                bridged = tr.reference_by_encoder();
                assert_eq!(bridged, !tr.seeking(), "bridged only once it stands");
            }
        }
        if bridged {
            break;
        }
    }
    assert!(bridged, "found again and bridged");
    assert_eq!(found, 2, "found on the way, and again once it stood");
    let n = b.moves.len();
    assert_eq!(
        b.moves[n - 2..],
        [150.0 - 0.02, 150.0],
        "by the final approach"
    );
    let st = tr.stitch();
    assert!(st.valid);
    // The stitch moved by the encoder; the carriage (stitch plus spot) reads where it stands,
    // to the follower's own error (3 µm here) and the PSD's noise.
    let spot = b.frame().spots[1].map_or(f64::NAN, |s| s.x);
    let carriage = st.follower_mm + spot - before;
    assert!((carriage - 150.0).abs() < 0.01, "read at {carriage:.4} mm");
    assert!(!tr.seek(150.0, b.now), "not lost: nothing to seek");
}

/// The spot on PSD2 (half-size 4.5 mm) as the overlap tracker lets it run: the carriage starts
/// from rest at 500 mm/s² to 100 mm/s over 100 mm, the follower (200 mm/s, 5000 mm/s²) does
/// nothing for `latency` after each command (the drive entering cyclic synchronous position)
/// and then goes to the commanded target carried on by its velocity. The largest |X2| seen.
fn spot_excursion(anticipate: Duration, latency: Duration) -> f64 {
    let t0 = crate::util::clock::now();
    let mut rng = Rng::new(21);
    let mut tr = Tracker::new(TrackSettings {
        strategy: Strategy::Overlap,
        anticipate,
        ..TrackSettings::default()
    });
    let (accel, top) = (500.0, 100.0);
    let carriage = |t: f64| {
        let t = t - 0.5; // at rest for the first 0.5 s
        if t <= 0.0 {
            0.0
        } else if t < top / accel {
            0.5 * accel * t * t
        } else {
            top * top / (2.0 * accel) + top * (t - top / accel)
        }
    };
    let (mut enc, mut vel) = (0.0_f64, 0.0_f64);
    // Commands waiting for the drive: (effective from, target at `at`, velocity, `at`).
    let mut queue: Vec<(f64, f64, f64, f64)> = Vec::new();
    let mut goal: Option<(f64, f64, f64)> = None;
    let mut worst = 0.0_f64;
    for k in 1..1500 {
        let t = k as f64 * 0.002;
        while let Some(i) = queue.iter().position(|q| q.0 <= t) {
            let (_, target, v, at) = queue.remove(i);
            goal = Some((target, v, at));
        }
        // The drive: towards the goal carried on to now, within its speed and acceleration.
        if let Some((target, v, at)) = goal {
            let aim = target + v * (t - at);
            let want = ((aim - enc) / 0.01 + v).clamp(-200.0, 200.0);
            vel += (want - vel).clamp(-5000.0 * 0.002, 5000.0 * 0.002);
            enc += vel * 0.002;
        }
        tr.handle_follower(
            FollowerState {
                position_mm: enc,
                ready: true,
                target_reached: goal.is_none(),
                at: Some(t0 + Duration::from_secs_f64(t)),
            },
            t0 + Duration::from_secs_f64(t),
        );
        let x = carriage(t) - enc;
        worst = worst.max(x.abs());
        let spot = (x.abs() <= 4.5).then(|| Spot {
            x: x + rng.gauss(1e-3),
            y: 0.0,
        });
        let other = Some(Spot { x: 0.0, y: 0.0 });
        let f = Frame {
            seq: k,
            at: t0 + Duration::from_secs_f64(t),
            unix_us: 0,
            spots: [other, spot, other],
            sums: [5.0; 3],
        };
        tr.handle_frame(&f, t0 + Duration::from_secs_f64(t));
        while let Some(c) = tr.poll_command() {
            let (target, v, at) = match c {
                FollowerCommand::MoveTo(m) => (m, 0.0, t),
                FollowerCommand::Follow {
                    target_mm,
                    velocity_mm_s,
                    at,
                } => (
                    target_mm,
                    velocity_mm_s,
                    at.saturating_duration_since(t0).as_secs_f64(),
                ),
            };
            let delay = if goal.is_none() && queue.is_empty() {
                latency.as_secs_f64()
            } else {
                0.0
            };
            queue.push((t + delay, target, v, at));
        }
    }
    worst
}

#[test]
fn a_carriage_starting_fast_keeps_the_spot_on_psd2_while_the_follower_starts() {
    let latency = Duration::from_millis(40);
    let kept = spot_excursion(Duration::from_millis(100), latency);
    assert!(kept < 4.0, "the spot ran to {kept:.2} mm with anticipation");
    // Following only at the edge (the default): the spot leaves PSD2 (this bench can tell).
    let lost = spot_excursion(Duration::ZERO, latency);
    assert!(lost > 4.5, "the spot ran to {lost:.2} mm at the edge only");
}

/// The follow commands a tracker sends while the head alone moves the spot on PSD2 from its
/// centre to 3 mm at 100 mm/s (a hexapod's pose; the follower stands at 0), over 1 s.
fn follows_of_a_pose(held: bool) -> usize {
    let t0 = crate::util::clock::now();
    let mut tr = Tracker::new(TrackSettings {
        strategy: Strategy::Overlap,
        anticipate: Duration::from_millis(100),
        ..TrackSettings::default()
    });
    tr.hold(held);
    let mut follows = 0;
    for k in 1..500 {
        let t = k as f64 * 0.002;
        let at = t0 + Duration::from_secs_f64(t);
        let still = FollowerState {
            position_mm: 0.0,
            ready: true,
            target_reached: true,
            at: Some(at),
        };
        tr.handle_follower(still, at);
        let x = (100.0 * (t - 0.2)).clamp(0.0, 3.0);
        let spot = Some(Spot { x, y: 0.0 });
        let f = Frame {
            seq: k,
            at,
            unix_us: 0,
            spots: [spot, spot, spot],
            sums: [5.0; 3],
        };
        tr.handle_frame(&f, at);
        while let Some(c) = tr.poll_command() {
            follows += usize::from(matches!(c, FollowerCommand::Follow { .. }));
        }
    }
    follows
}

/// A hexapod calibration holds the follower and moves the head: a spot that runs fast
/// within PSD2 and stops there is not a carriage running out, and a held follower is not
/// sent after it by anticipation (with it, the console's hexapod run fitted its calibration
/// 226 times off its bound).
#[test]
fn a_held_follower_is_not_sent_after_a_spot_by_anticipation() {
    assert!(follows_of_a_pose(false) > 0, "free: anticipation follows");
    assert_eq!(follows_of_a_pose(true), 0, "held: no follow command");
}

/// A service that restarts mid-run takes its zero back with the stitch it was taken with,
/// and bridges from there by the encoder: PSD2's vertical offset and position are the
/// follower's shape between the zero and where it stands now, as if the service had never
/// stopped. Referencing afresh where the follower stood after the restart dropped that shape
/// (roll 0.8″ off after a SIGKILL in the storm, issue 24).
#[test]
fn a_restarted_tracker_bridges_from_where_the_stitch_stood_at_the_zero() {
    for strategy in [Strategy::Encoder, Strategy::Overlap] {
        let map = Arc::new(bench_map());
        let (mut b, mut tr) = referenced(strategy);
        tr.set_map(Some(map.clone()));
        b.run(&mut tr, 100);
        assert!(tr.reference());
        let anchor = tr.anchor().expect("a valid stitch has an anchor");
        let (e0, u0, v0) = (b.enc, fu(b.enc), fv(b.enc));
        // The carriage runs 50 mm; the service dies there, and a new one starts.
        for _ in 0..2500 {
            b.carriage += 10.0 * 0.002;
            b.step(&mut tr);
        }
        b.run(&mut tr, 2000);
        let kept = tr.stitch();
        let mut restarted = Tracker::new(TrackSettings {
            strategy,
            ..TrackSettings::default()
        });
        restarted.set_map(Some(map.clone()));
        restarted.restore(&anchor);
        assert!(!restarted.stitch().valid, "invalid until bridged");
        b.run(&mut restarted, 100);
        assert!(restarted.anchored());
        assert!(restarted.reference_by_encoder());
        let s = restarted.stitch();
        assert!(s.valid);
        let true_u = b.enc + fu(b.enc) - u0 + e0;
        let true_v = fv(b.enc) - v0;
        assert!(
            true_v.abs() > 1e-3,
            "the shape a fresh reference would drop is {:.2} µm",
            true_v * 1e3
        );
        // The map's interpolation is within 2 nm of the bench's sines; the service that
        // went on stitched with the PSD's 1 µm noise averaged.
        for (what, got, truth, within) in [
            ("along", s.follower_mm, true_u, 3e-6),
            ("vertical", s.vertical_mm, true_v, 3e-6),
            ("along, as kept", s.follower_mm, kept.follower_mm, 0.3e-3),
            ("vertical, as kept", s.vertical_mm, kept.vertical_mm, 0.3e-3),
        ] {
            assert!(
                (got - truth).abs() < within,
                "{strategy:?} {what}: {got:.6} mm vs {truth:.6} mm"
            );
        }
        // One bridge from the zero's place, with the map's uncertainty.
        assert!(
            s.variance[0] > 0.0 && s.variance[1] > 0.0,
            "{:?}",
            s.variance
        );
    }
}

/// An encoder step whose recorded start is not where the stitch stands (the follower moved in
/// between, a step the tracker never saw end) is bridged from the stitch: counting from the
/// recorded start put a storm's stitch 3.79 mm off its encoder, and no stop was ever on a
/// target again (issue 24).
#[test]
fn an_encoder_step_is_bridged_from_where_the_stitch_stands() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    b.run(&mut tr, 100);
    let before = tr.stitch().follower_mm;
    // A start recorded 5.79 mm away, as after the storm's following error.
    tr.encoder_before = b.enc + 5.79;
    tr.finish_encoder_step(b.now);
    let after = tr.stitch().follower_mm;
    assert!(
        (after - before).abs() < 1e-6,
        "the stitch moved by {:.3} mm with the follower standing",
        after - before
    );
}

/// The stitch in flight counts from the same place: with a step's start recorded 2.46 mm
/// below the stitch's, a carriage the follower followed read 2.46 mm past where it stood,
/// and the run took the stop as approached from above (issue 24).
#[test]
fn the_stitch_in_flight_counts_from_where_the_stitch_stands() {
    let (mut b, mut tr) = referenced(Strategy::Overlap);
    b.run(&mut tr, 100);
    let before = tr.stitch().follower_mm;
    tr.encoder_before = b.enc - 2.46;
    tr.phase = Phase::Moving {
        target: b.enc,
        via: None,
        since: b.now,
        reached_at: None,
    };
    let in_flight = tr.stitch().follower_mm;
    assert!(
        (in_flight - before).abs() < 1e-6,
        "in flight the stitch moved by {:.3} mm with the follower standing",
        in_flight - before
    );
}
