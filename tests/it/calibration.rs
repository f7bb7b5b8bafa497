//! Calibration on a head with installation errors reaches the noise limit (must show 3).

use axiscomp::optics::Layout;
use axiscomp::sim::study::{StudySpec, run_study};
use axiscomp::sim::{InstallSpec, PoseWindow};
use axiscomp::units::{DOF_NAMES, Errors6};

fn ratios(measured: &Errors6, bound: &Errors6) -> [f64; 6] {
    let (m, b) = (measured.to_array(), bound.to_array());
    std::array::from_fn(|k| m[k] / b[k])
}

fn assert_within(label: &str, r: [f64; 6], limit: f64) {
    for k in 0..6 {
        assert!(
            r[k] <= limit,
            "{label}: hold-out RMS of {} is {:.3}× the Cramér–Rao bound (limit {limit})",
            DOF_NAMES[k],
            r[k]
        );
    }
}

fn spec(seed: u64, travels: Vec<f64>, holdout_travel: (f64, f64)) -> StudySpec {
    StudySpec {
        seed,
        install: InstallSpec {
            offset_mm: 0.5,
            tilt_deg: 0.2,
            gain_error: 0.01,
        },
        noise_mm: 1e-3,
        poses: 200,
        window: PoseWindow {
            travels,
            ..PoseWindow::default()
        },
        holdout: 2000,
        holdout_travel,
        ..StudySpec::default()
    }
}

/// Hexapod at one position, hold-out poses in the same window: both the linear β with offset
/// and the model-based calibration reach 1.15× the bound on every DOF, for several heads.
#[test]
fn calibration_at_one_position_reaches_the_bound() {
    let layout = Layout::reference();
    for seed in [1, 2, 3] {
        let r = run_study(&layout, &spec(seed, vec![0.0], (0.0, 0.0)), false).unwrap();
        assert_eq!(r.calibration_poses, 200);
        let model = r.model.expect("model fitted");
        assert_within(&format!("seed {seed} model"), ratios(&model, &r.crlb), 1.15);
        assert_within(
            &format!("seed {seed} linear"),
            ratios(&r.linear, &r.crlb),
            1.15,
        );
        // Without calibration the installation errors bias the result beyond the noise (twice
        // the bound at least, at this one position, on a head whose beams the factory aligned).
        let sim = ratios(&r.simulated_zero_ref, &r.crlb);
        assert!(
            sim.iter().any(|x| *x > 2.0),
            "simulated β too good: {sim:?}"
        );
    }
}

/// Hexapod at three bench positions, hold-out anywhere over 0..200 mm: the model-based
/// calibration holds over the travel; a fixed β does not.
#[test]
fn model_calibration_holds_over_the_travel() {
    let layout = Layout::reference();
    let r = run_study(
        &layout,
        &spec(7, vec![0.0, 100.0, 200.0], (0.0, 200.0)),
        false,
    )
    .unwrap();
    let model = r.model.expect("model fitted");
    assert_within("model over travel", ratios(&model, &r.crlb), 1.15);
    let lin = ratios(&r.linear, &r.crlb);
    assert!(
        lin.iter().any(|x| *x > 3.0),
        "fixed β unexpectedly good: {lin:?}"
    );
    let cal = &r.calibration;
    assert!(cal.model.as_ref().is_some_and(|m| m.converged));
}

/// The service calibrates its head (the console's Calibrate screen) from the pose set the
/// README's command makes for the twin (`calibrate simulate --twin CONFIG`): a twin whose head
/// has installation errors (±0.5 mm / ±0.2°, seed 21) is fitted through the control API,
/// judged plausible, accepted and stored; from then on the live errors at rest are the twin's
/// truth within 3σ (the live window's sd and the calibration's hold-out error), where the
/// nominal decoupling was hundreds of µm off. A pose set of another head (the command's own
/// random head) fits as well but reads implausibly here: it is refused without the override,
/// says why, and is accepted with it. A bad path is named; accept with nothing waiting is
/// refused.
#[tokio::test(start_paused = true)]
async fn the_service_fits_accepts_and_uses_a_calibration() {
    use crate::helpers::{RigOptions, ServiceRig};
    use axiscomp::service::api::Request;

    let dir = std::env::temp_dir().join(format!("axiscomp-svc-cal-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    // The twin's configuration: configs/sim.toml with a head that has installation errors.
    let sim_toml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/configs/sim.toml"))
            .expect("configs/sim.toml")
            .replace("seed = 1\n", "seed = 21\n")
            .replace("install_offset_mm = 0.0", "install_offset_mm = 0.5")
            .replace("install_tilt_deg = 0.0", "install_tilt_deg = 0.2");
    let twin_config = dir.join("sim.toml");
    std::fs::write(&twin_config, &sim_toml).expect("twin config");
    let (_, twin) = axiscomp::sim::config::load(&twin_config).expect("the twin config");
    assert_eq!(twin.plant.seed, 21);
    assert_eq!(twin.plant.install.offset_mm, 0.5);
    let opts = RigOptions {
        service_toml: "[tracking]\nstrategy = \"overlap\"\n".into(),
        plant: twin.plant.clone(),
        ..RigOptions::default()
    };
    // The README's command for the twin's own head, and the command's own random head.
    let own = dir.join("poses.csv");
    let other = dir.join("other-head.csv");
    for (args, out) in [
        (vec!["--twin", twin_config.to_str().expect("path")], &own),
        (vec!["--seed", "5"], &other),
    ] {
        let o = crate::helpers::bin()
            .args(["calibrate", "simulate", "--poses", "60", "--output"])
            .arg(out)
            .args(args)
            .output()
            .expect("axiscomp calibrate simulate");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }

    let rig = ServiceRig::start(opts).await;
    let (before, _) = live_deviation(&rig).await;
    let status = rig.request(Request::Calibration).await.expect("status");
    assert!(
        status["active"].is_null() && status["pending"].is_null(),
        "{status}"
    );

    let e = rig
        .request(Request::CalibrationAccept { force: false })
        .await
        .expect_err("nothing waits");
    assert!(e.to_string().contains("fit a pose set first"), "{e}");
    let e = rig
        .request(Request::CalibrationFit {
            poses: dir.join("missing.csv").display().to_string(),
        })
        .await
        .expect_err("no such file");
    assert!(e.to_string().contains("missing.csv"), "{e}");

    // Another head's pose set: it fits, but reads hundreds of µm here.
    let fitted = fit(&rig, &other).await;
    let concerns = fitted["pending"]["concerns"].as_array().expect("concerns");
    assert!(!concerns.is_empty(), "{fitted}");
    let e = rig
        .request(Request::CalibrationAccept { force: false })
        .await
        .expect_err("implausible");
    let e = e.to_string();
    eprintln!("another head's calibration: {e}");
    assert!(
        e.contains("not accepted") && e.contains("another head") && e.contains("force"),
        "{e}"
    );
    let status = rig.request(Request::Calibration).await.expect("status");
    assert!(
        status["active_id"].is_null() && !status["pending"].is_null(),
        "{status}"
    );
    let forced = rig
        .request(Request::CalibrationAccept { force: true })
        .await
        .expect("accepted with the override");
    assert!(
        !forced["overridden"]
            .as_array()
            .expect("overridden")
            .is_empty(),
        "{forced}"
    );

    // The twin's own head: plausible, accepted without the override.
    let fitted = fit(&rig, &own).await;
    let pending = &fitted["pending"];
    assert_eq!(pending["rank"], 7, "{fitted}");
    assert_eq!(pending["decoupling"], "model");
    assert_eq!(pending["concerns"], serde_json::json!([]), "{fitted}");
    let holdout: Vec<f64> = pending["model_holdout"]
        .as_array()
        .expect("hold-out")
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect();
    let accepted = rig
        .request(Request::CalibrationAccept { force: false })
        .await
        .expect("accept");
    let id = accepted["calibration_id"].as_i64().expect("stored id");
    let status = rig.request(Request::Calibration).await.expect("status");
    assert_eq!(status["active_id"], id);
    assert!(status["pending"].is_null());

    let (after, sd) = live_deviation(&rig).await;
    eprintln!(
        "|live − truth| before {before:.2?}, after {after:.2?} (sd {sd:.2?}, hold-out RMS {holdout:.2?})"
    );
    assert!(
        before.iter().take(3).any(|d| *d > 50.0),
        "the nominal decoupling should be far off on this head: {before:?}"
    );
    for k in 0..6 {
        let sigma = (sd[k] * sd[k] + holdout[k] * holdout[k]).sqrt();
        assert!(
            after[k] <= 3.0 * sigma,
            "{}: |live − truth| {:.3} after accepting, beyond 3σ = {:.3}",
            DOF_NAMES[k],
            after[k],
            3.0 * sigma
        );
    }
    rig.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

async fn fit(rig: &crate::helpers::ServiceRig, poses: &std::path::Path) -> serde_json::Value {
    use axiscomp::service::api::Request;
    crate::helpers::within_s(
        300,
        "the fit",
        rig.request(Request::CalibrationFit {
            poses: poses.display().to_string(),
        }),
    )
    .await
    .expect("fit")
}

/// |live − truth| per DOF (user units) over a fresh window at rest at D = 0 (no zero
/// reference: the decoupling alone), and the stated sd.
async fn live_deviation(rig: &crate::helpers::ServiceRig) -> ([f64; 6], [f64; 6]) {
    use axiscomp::service::api::Request;
    use std::time::Duration;
    rig.request(Request::Nominal { mm: None })
        .await
        .expect("clear");
    rig.request(Request::Nominal { mm: Some(0.0) })
        .await
        .expect("nominal");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let s = rig
        .wait_for(30, "a live window", |s| {
            // Frames late on a loaded machine are left out of the window: half of it will do
            // (the stated sd grows accordingly).
            s.live
                .as_ref()
                .is_some_and(|l| l.nominal_mm == Some(0.0) && l.frames >= 50)
        })
        .await;
    let truth = rig
        .twin
        .plant
        .truth(axiscomp::util::clock::now())
        .errors
        .to_user();
    let live = s.live.expect("live");
    (
        std::array::from_fn(|k| (live.errors[k] - truth[k]).abs()),
        live.sd,
    )
}

/// The calibration's standard uncertainty in the budget (issue 14), judged by the truth: the
/// calibrated model's own error, read noise-free at 500 fresh poses over the travel, is
/// covered by it on every DOF, for several heads; and it comes from hold-out poses averaged
/// as a bench dwells, so it is not the single-frame noise's allowance (a fifth of the bound
/// or more, which alone made roll's U 0.89″ at the zero).
#[test]
fn the_calibrations_stated_u_covers_its_true_error() {
    use axiscomp::optics::Pose;
    use axiscomp::sim::Rng;
    let layout = Layout::reference();
    for seed in [3, 7, 11] {
        let mut s = spec(seed, vec![0.0, 100.0, 200.0], (0.0, 200.0));
        s.holdout = 1000;
        let r = run_study(&layout, &s, false).unwrap();
        let (u, source) = r.calibration_u().expect("a model fitted");
        assert!(source.contains("mean of 50 frames"), "{source}");
        let dec = r.calibration.decoupler(&layout).expect("decoupler");
        let half = s.window.half_range.to_array();
        let mut rng = Rng::new(seed + 1000);
        let (mut sum, mut n) = ([0.0; 6], 0);
        while n < 500 {
            let e = Errors6::from_array(std::array::from_fn(|k| rng.uniform(-half[k], half[k])));
            let d = rng.uniform(0.0, 200.0);
            let pose = Pose::new(e, d, d);
            let Some(readings) = r.head.exact(&pose).vector() else {
                continue;
            };
            let est = dec.decouple(&readings, d, d).expect("decouple");
            let (m, t) = (est.errors.to_array(), e.to_array());
            for k in 0..6 {
                sum[k] += (m[k] - t[k]).powi(2);
            }
            n += 1;
        }
        let truth: [f64; 6] = sum.map(|x| (x / n as f64).sqrt());
        let single = r.crlb.to_array();
        for k in 0..6 {
            eprintln!(
                "seed {seed} {}: model's true error {:.3e}, stated u {:.3e}, single-frame bound {:.3e}",
                DOF_NAMES[k], truth[k], u[k], single[k]
            );
            assert!(
                truth[k] <= 1.15 * u[k],
                "seed {seed} {}: the model errs by {:e} RMS, the stated u is {:e}",
                DOF_NAMES[k],
                truth[k],
                u[k]
            );
            assert!(
                u[k] < 0.5 * single[k],
                "seed {seed} {}: stated u {:e} against the single-frame bound {:e}",
                DOF_NAMES[k],
                u[k],
                single[k]
            );
        }
    }
}
