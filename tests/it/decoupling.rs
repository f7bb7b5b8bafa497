//! Decoupling recovers what the forward model was given (must show 2).

use axiscomp::Errors6;
use axiscomp::decouple::{SolveOptions, solve_nonlinear};
use axiscomp::optics::{Layout, Pose};
use axiscomp::sim::{InstallSpec, Rng, TwinHead};
use proptest::prelude::*;

fn errors_strategy() -> impl Strategy<Value = [f64; 6]> {
    (
        -50.0..50.0f64,
        -50.0..50.0f64,
        -50.0..50.0f64,
        -30.0..30.0f64,
        -30.0..30.0f64,
        -30.0..30.0f64,
    )
        .prop_map(|(a, b, c, d, e, f)| [a, b, c, d, e, f])
}

fn check_recovery(layout: &Layout, user: [f64; 6], travel: f64, follower: f64) {
    let e = Errors6::from_user(user);
    let pose = Pose::new(e, travel, follower);
    let r = layout
        .forward(&pose)
        .vector()
        .expect("every PSD sees its spot in this window");
    let est = solve_nonlinear(
        layout,
        &r,
        travel,
        follower,
        &[1e-3; 6],
        &SolveOptions::default(),
    )
    .expect("decoupling converges");
    let got = est.errors.to_user();
    for k in 0..6 {
        // 1e-3 µm for translations, 1e-3 arcsec for rotations.
        assert!(
            (got[k] - user[k]).abs() < 1e-3,
            "DOF {k}: recovered {} for {} (D {travel}, d {follower})",
            got[k],
            user[k]
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// Random errors within ±50 µm / ±30″ at travel 0..200 mm, the follower within ±2 mm of
    /// the spot: the nonlinear decoupling recovers them to 1e-3 µm / 1e-3″ without noise.
    #[test]
    fn nonlinear_decoupling_recovers_errors(
        user in errors_strategy(),
        travel in 0.0..200.0f64,
        lag in -2.0..2.0f64,
    ) {
        check_recovery(&Layout::reference(), user, travel, travel + lag);
    }

    /// The same on a head with installation errors, decoupled with its true model.
    #[test]
    fn nonlinear_decoupling_recovers_errors_on_a_perturbed_head(
        user in errors_strategy(),
        travel in 0.0..200.0f64,
        lag in -1.0..1.0f64,
        seed in 0u64..8,
    ) {
        let head = TwinHead::random(
            &Layout::reference(),
            &InstallSpec { gain_error: 0.01, ..InstallSpec::default() },
            0.0,
            &mut Rng::new(seed),
        ).expect("aligned head");
        check_recovery(&head.truth, user, travel, travel + lag);
    }
}
