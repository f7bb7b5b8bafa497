//! The map from synthetic steps of the twin's follower model (the lab test in
//! `tests/it/follower.rs` runs the whole chain).

use super::*;
use crate::sim::Rng;
use crate::sim::follower::{FollowerModel, FollowerSpec, Motion};

fn motion(d: Direction) -> Motion {
    match d {
        Direction::Up => Motion::Up,
        Direction::Down => Motion::Down,
    }
}

/// Steps of `passes` stop-and-go passes (up, down, …) over 0..travel every `step` mm, with a
/// back-and-forth probe every 50 mm; PSD2 with a gain error of `gain` and `sd` (mm) of noise
/// per step.
fn steps(
    m: &FollowerModel,
    travel: f64,
    step: f64,
    passes: usize,
    gain: f64,
    sd: f64,
) -> Vec<Step> {
    let mut rng = Rng::new(77);
    let mut path = vec![0.0];
    for p in 0..passes {
        let n = (travel / step) as usize;
        for k in 1..=n {
            let x = if p % 2 == 0 {
                k as f64 * step
            } else {
                (n - k) as f64 * step
            };
            path.push(x);
            if k % 13 == 0 {
                let back = if p % 2 == 0 { x - step } else { x + step };
                path.push(back);
                path.push(x);
            }
        }
    }
    let mut out = Vec::new();
    let mut dir = Direction::Up;
    for w in path.windows(2) {
        let (a, b) = (w[0], w[1]);
        let nd = if b >= a {
            Direction::Up
        } else {
            Direction::Down
        };
        let true_a = a + m.along(a, motion(dir));
        let true_b = b + m.along(b, motion(nd));
        out.push(Step {
            from_mm: a,
            to_mm: b,
            along_mm: (true_b - true_a) * (1.0 + gain) + rng.gauss(sd),
            // PSD2 tilted in its plane by 3 mrad: a jump in proportion to the step.
            vertical_mm: (m.vertical(b) - m.vertical(a) + 3e-3 * (b - a)) * (1.0 + gain)
                + rng.gauss(sd),
            variance: [sd * sd; 2],
        });
        dir = nd;
    }
    out
}

#[test]
fn the_map_recovers_the_followers_errors_from_its_steps_and_certificate() {
    let spec = FollowerSpec::default();
    let m = FollowerModel::new(spec, 300.0, &mut Rng::new(3));
    let sd = 0.045e-3;
    let st = steps(&m, 300.0, 3.75, 4, 6e-5, sd);
    let cert = Certificate::parse(&m.certificate(&mut Rng::new(4)), "twin.csv").unwrap();
    let map = build(&st, Some(&cert), &MapSettings::default()).unwrap();
    assert_eq!(map.sources.long, Source::Certificate);
    assert_eq!(map.sources.vertical, Source::SelfCalibration);
    let sc = map.self_calibration.unwrap();
    assert!(sc.chi2_along < 2.0 && sc.chi2_vertical < 2.0, "{sc:?}");
    // The twin's stage repeats exactly: what its steps leave beyond the map is below their
    // own noise (the χ² bound for this many steps), not the 0.5 µm a certificate alone states.
    let beyond = sc.unmapped_sd_mm().unwrap();
    assert!(beyond < sd, "{beyond} against the steps' {sd} mm");
    let p = map.periodic.unwrap();
    assert!(
        (p.amplitude() - 1e-3).abs() < 0.05e-3,
        "periodic {}",
        p.amplitude()
    );
    let r = map.reversal.unwrap();
    assert!(
        (r.value_mm - 1e-3).abs() < 4.0 * r.u_mm.max(0.01e-3),
        "{r:?}"
    );
    // Vertical within 3 u of the truth's straightness to its end-point line everywhere.
    let vp = &map.vertical_positions_mm;
    let (x0, x1) = (vp[0], vp[vp.len() - 1]);
    let line = |x: f64| m.vertical(x0) + (m.vertical(x1) - m.vertical(x0)) * (x - x0) / (x1 - x0);
    for (i, &x) in vp.iter().enumerate() {
        let err = map.vertical_mm[i] - (m.vertical(x) - line(x));
        assert!(
            err.abs() <= 3.0 * map.vertical_u_mm[i] + 1e-9,
            "at {x}: {err} vs u {}",
            map.vertical_u_mm[i]
        );
    }
    // Along: differences between positions within the certificate's uncertainty.
    for k in 0..300 {
        let x = k as f64;
        for dir in [Direction::Up, Direction::Down] {
            let got = map.correction(x, dir)[0] - map.correction(0.0, Direction::Up)[0];
            let want = m.along(x, motion(dir)) - m.along(0.0, Motion::Up);
            let u = map
                .point(x, dir)
                .along_u_um
                .hypot(map.point(0.0, Direction::Up).along_u_um)
                * 1e-3;
            assert!(
                (got - want).abs() < 3.0 * u,
                "at {x} {dir:?}: {got} vs {want} (u {u})"
            );
        }
    }
    // TOML round trip.
    let back = FollowerMap::from_toml(&map.to_toml(), "map.toml").unwrap();
    assert_eq!(back, map);
    assert!(map.to_csv(1.0).lines().count() > 300);
}

#[test]
fn a_certificate_alone_maps_the_along_axis_only() {
    let m = FollowerModel::new(FollowerSpec::default(), 200.0, &mut Rng::new(5));
    let cert = Certificate::parse(&m.certificate(&mut Rng::new(6)), "twin.csv").unwrap();
    let map = build(&[], Some(&cert), &MapSettings::default()).unwrap();
    assert_eq!(map.sources.vertical, Source::None);
    assert_eq!(map.sources.periodic, Source::None);
    assert_eq!(map.correction(50.0, Direction::Up)[1], 0.0);
    let got = map.correction(50.0, Direction::Down)[0];
    assert!((got - m.along(50.0, Motion::Down)).abs() < 1e-3);
    assert!(matches!(
        build(&[], None, &MapSettings::default()),
        Err(MapError::Empty)
    ));
}

/// An outside reference's line is added to the vertical map, its uncertainty growing with the
/// distance from its origin.
#[test]
fn a_referenced_line_adds_to_the_vertical_map() {
    let steps: Vec<Step> = Vec::new();
    let cert = Certificate::parse(
        "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n100,1,+,0.2\n",
        "c.csv",
    )
    .unwrap();
    let mut map = build(&steps, Some(&cert), &MapSettings::default()).unwrap();
    let before = map.point(60.0, Direction::Up);
    map.vertical_line = Some(VerticalLine {
        origin_mm: 10.0,
        slope: 2e-6,
        u_slope: 0.5e-6,
        source: "a level".into(),
    });
    let after = map.point(60.0, Direction::Up);
    assert!((after.vertical_um - before.vertical_um - 0.1).abs() < 1e-9);
    assert!((after.vertical_u_um - 0.025).abs() < 1e-9);
    assert_eq!(after.along_um, before.along_um);
}

#[test]
fn the_stage_beyond_its_map_is_the_steps_scatter_beyond_their_noise() {
    let sc = |chi2: f64, steps: usize, step_sd_along_mm: f64| SelfCalibration {
        steps,
        reversals: 0,
        chi2_along: chi2,
        chi2_vertical: 1.0,
        machine_time_s: None,
        step_sd_along_mm,
    };
    // 200 steps of 0.4 µm stated noise scattering as 0.5 µm: χ² = 0.25/0.16 = 1.5625 (the
    // stage 0.21 µm beyond its map); its bound adds 2·√(2/200) = 0.2, so σ² = (1.7625 − 1)·0.16/2
    // µm², 0.25 µm.
    let b = sc(1.5625, 200, 0.4e-3).unmapped_sd_mm().unwrap();
    assert!(
        (b - (0.7625f64 * 0.16 / 2.0).sqrt() * 1e-3).abs() < 1e-12,
        "{b}"
    );
    // A map stored before the steps' noise was kept says nothing: the settings state it.
    assert_eq!(sc(1.0, 200, 0.0).unmapped_sd_mm(), None);
    assert_eq!(sc(1.0, 0, 0.4e-3).unmapped_sd_mm(), None);
}

/// What two positions share of the map cancels in their difference: a position against
/// itself differs by nothing, two far apart by both their variances, two in one interval by
/// what their weights differ; the reversal only between directions.
#[test]
fn the_maps_difference_between_two_positions_cancels_what_they_share() {
    let m = FollowerModel::new(FollowerSpec::default(), 200.0, &mut Rng::new(5));
    let cert = Certificate::parse(&m.certificate(&mut Rng::new(6)), "twin.csv").unwrap();
    let mut map = build(&[], Some(&cert), &MapSettings::default()).unwrap();
    map.vertical_positions_mm = vec![0.0, 50.0, 100.0, 150.0];
    map.vertical_mm = vec![0.0; 4];
    map.vertical_u_mm = vec![0.0, 30e-6, 40e-6, 50e-6];
    map.reversal = Some(Estimate {
        value_mm: 1e-3,
        u_mm: 4e-6,
    });
    let (up, down) = (Direction::Up, Direction::Down);
    assert_eq!(map.difference_variance(42.0, 42.0, up, up), [0.0, 0.0]);
    // 0.5 of one long point (10 mm apart) moves between 40 and 45 mm; the vertical's 50 mm
    // point by 0.1 of its weight.
    let u_long = map.long_u_mm[4];
    let near = map.difference_variance(40.0, 45.0, up, up);
    assert!(
        (near[0] - 2.0 * (0.5 * u_long).powi(2)).abs() < 1e-18,
        "{near:?}"
    );
    let v = 0.1f64.powi(2) * (30e-6f64.powi(2) + 0.0);
    assert!((near[1] - v).abs() < 1e-20, "{near:?} against {v:e}");
    // Far apart: both points' variances, as `point` states them.
    let far = map.difference_variance(50.0, 150.0, up, up);
    let (pa, pb) = (map.point(50.0, up), map.point(150.0, up));
    let both = (pa.vertical_u_um.powi(2) + pb.vertical_u_um.powi(2)) * 1e-6;
    assert!((far[1] - both).abs() < 1e-18, "{far:?} against {both:e}");
    // The reversal between two directions.
    let turned = map.difference_variance(42.0, 42.0, up, down);
    assert!((turned[0] - 16e-12).abs() < 1e-20, "{turned:?}");
}
