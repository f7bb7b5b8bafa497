//! The live service against the digital twin, over the real protocols on loopback (Modbus TCP
//! to the I/O module, CANopen over a cannelloni UDP pair to the follower drive, the control API
//! on a Unix socket): tracking and stitching over 100 mm for both strategies, compared with the
//! twin's truth, and the faults (issue 3).

use crate::helpers::{RigOptions, ServiceRig};
use axiscomp::service::control::Request;
use axiscomp::service::snapshot::Snapshot;
use axiscomp::sim::plant::Truth;
use axiscomp::track::Strategy;
use axiscomp::units::DOF_NAMES;
use std::time::{Duration, Instant};

/// Handovers quicker than the production defaults, so the stepped run stays short; the
/// statistics are the same (100 frames each side).
const FAST_TRACKING: &str = "[tracking]\nrest_ms = 200\naverage_frames = 100\nsettle_ms = 100\n";

fn rig_options(strategy: &str) -> RigOptions {
    RigOptions {
        service_toml: format!("{FAST_TRACKING}strategy = \"{strategy}\"\n"),
        ..RigOptions::default()
    }
}

/// Whether the live errors are within `k` stated standard deviations of `expected` (user
/// units) on every DOF; the worst |z| and its DOF.
fn within_k_sd(s: &Snapshot, expected: &[f64; 6], k: f64) -> (bool, f64, &'static str) {
    let live = s.live.as_ref().expect("live errors");
    let mut worst = (0.0, "");
    for d in 0..6 {
        let z = (live.errors[d] - expected[d]).abs() / live.sd[d];
        if z > worst.0 {
            worst = (z, DOF_NAMES[d]);
        }
    }
    (worst.0 <= k, worst.0, worst.1)
}

/// The truth of the six errors at `now` relative to `at_zero` (user units): what the service
/// shows after a zero reference.
fn relative(now: &Truth, at_zero: &Truth) -> [f64; 6] {
    let (a, b) = (now.errors.to_user(), at_zero.errors.to_user());
    std::array::from_fn(|k| a[k] - b[k])
}

/// A fresh live window, decoupled at `nominal`, once the carriage is at rest there.
async fn fresh_window(rig: &ServiceRig, nominal: f64) -> Snapshot {
    rig.request(Request::Nominal { mm: Some(nominal) })
        .await
        .expect("nominal");
    // The window restarts with the nominal; wait until it is full again.
    tokio::time::sleep(Duration::from_millis(300)).await;
    rig.wait_for(10, "a full live window", |s| {
        s.live
            .as_ref()
            .is_some_and(|l| l.nominal_mm == Some(nominal) && l.frames >= 100)
    })
    .await
}

/// Check the live errors against the truth within 3 stated sd on every DOF. A correct
/// estimator exceeds 3 sd on a DOF 0.27 % of the time; one fresh, independent window is taken
/// before failing, so a spurious failure has odds of about 1e-5.
async fn assert_matches_truth(rig: &ServiceRig, nominal: f64, at_zero: &Truth, label: &str) -> f64 {
    let mut worst_seen = 0.0;
    for attempt in 0..2 {
        let s = fresh_window(rig, nominal).await;
        let truth = rig.twin.plant.truth(Instant::now());
        let expected = relative(&truth, at_zero);
        let (ok, worst, dof) = within_k_sd(&s, &expected, 3.0);
        worst_seen = worst;
        if ok {
            return worst;
        }
        eprintln!(
            "{label}: attempt {attempt}: {dof} at {worst:.2} sd; live {:?} truth {expected:?}",
            s.live
        );
        rig.request(Request::Nominal { mm: None })
            .await
            .expect("clear nominal");
    }
    panic!("{label}: live errors not within 3 sd of the truth (worst {worst_seen:.2} sd)");
}

/// Step (overlap) or drive (encoder) the carriage from 0 to 100 mm and compare the live six
/// errors and the stitched positioning with the twin's truth.
async fn hundred_mm(strategy: Strategy) {
    let name = format!("{strategy:?}").to_lowercase();
    let rig = ServiceRig::start(rig_options(&name)).await;
    // Zero reference at D = 0.
    rig.request(Request::Nominal { mm: Some(0.0) })
        .await
        .expect("nominal 0");
    let zero = rig.request(Request::Zero).await.expect("zero");
    assert_eq!(zero["zeroed"], true);
    let at_zero = rig.twin.plant.truth(Instant::now());
    let s0 = rig.snapshot().await;
    let ref_follower = s0.tracking.follower_mm;
    let ref_true = rig.twin.plant.truth(Instant::now()).follower_true;
    assert_matches_truth(&rig, 0.0, &at_zero, "at 0 mm").await;
    rig.request(Request::Nominal { mm: None })
        .await
        .expect("clear nominal");

    // Watch PSD2 while the carriage goes: the spot must stay on it throughout.
    let watch_rig_socket = rig.socket.clone();
    let watching = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let w = watching.clone();
    let watcher = tokio::spawn(async move {
        let mut c = axiscomp::service::control::Client::connect(&watch_rig_socket)
            .await
            .expect("client");
        c.subscribe(Some(50.0)).await.expect("subscribe");
        let (mut seen, mut lost, mut max_x2) = (0usize, 0usize, 0.0f64);
        while w.load(std::sync::atomic::Ordering::Relaxed) {
            let s = c.next_snapshot().await.expect("snapshot");
            if let Some(p) = &s.psd {
                seen += 1;
                match p.spots_um[1] {
                    Some([x, _]) => max_x2 = max_x2.max(x.abs()),
                    None => lost += 1,
                }
            }
        }
        (seen, lost, max_x2)
    });
    match strategy {
        Strategy::Overlap => {
            // 30 steps of 3.33 mm: each leaves the spot past the handover threshold (1.5 mm) and
            // short of the edge (3.5 mm), at rest.
            for k in 1..=30 {
                let d = 100.0 * k as f64 / 30.0;
                let before = rig.snapshot().await.tracking.handovers;
                rig.twin.move_and_wait(d).await;
                rig.wait_for(20, "the handover after a step", |s| {
                    s.tracking.handovers > before && s.tracking.at_rest
                })
                .await;
            }
        }
        Strategy::Encoder => {
            rig.twin.move_and_wait(100.0).await;
            rig.wait_for(20, "the follower centred and at rest", |s| {
                s.tracking.at_rest
                    && s.psd
                        .as_ref()
                        .and_then(|p| p.spots_um[1])
                        .is_some_and(|[x, _]| x.abs() < 300.0)
            })
            .await;
        }
    }
    watching.store(false, std::sync::atomic::Ordering::Relaxed);
    let (seen, lost, max_x2) = watcher.await.expect("watcher");
    assert!(seen > 20, "snapshots seen while moving: {seen}");
    assert_eq!(lost, 0, "PSD2 lost the spot in {lost} of {seen} snapshots");
    assert!(max_x2 < 4500.0, "spot at {max_x2} µm: off PSD2");

    // Compare once the service's view of the follower is the plant's (the follower at rest).
    let (s, truth) = {
        let end = Instant::now() + Duration::from_secs(10);
        loop {
            let s = rig.snapshot().await;
            let truth = rig.twin.plant.truth(Instant::now());
            let seen = s.follower.position_mm.expect("follower position");
            if (seen - truth.follower_encoder).abs() < 1e-3 {
                break (s, truth);
            }
            assert!(
                Instant::now() < end,
                "the follower keeps moving: service sees {seen} mm, plant {} mm",
                truth.follower_encoder
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    };
    assert!(s.tracking.valid, "{:?}", s.tracking);
    assert!(s.alarms.iter().all(|a| !a.active), "alarms: {:?}", s.alarms);
    // PSD2's position: stitched against the truth, within the stated stitching uncertainty.
    let stitched = s.tracking.follower_mm - ref_follower;
    let true_moved = truth.follower_true - ref_true;
    let sd_mm = s.tracking.sd_um[0] * 1e-3;
    eprintln!(
        "{name}: PSD2 stitched {stitched:.6} mm, true {true_moved:.6} mm, diff {:.3} µm, stated sd {:.3} µm, {} handovers",
        (stitched - true_moved) * 1e3,
        sd_mm * 1e3,
        s.tracking.handovers
    );
    assert!(sd_mm > 0.0);
    assert!(
        (stitched - true_moved).abs() <= 3.0 * sd_mm,
        "stitching outside 3 sd"
    );
    // The six errors at 100 mm, zeroed at 0: dy is the positioning over the 100 mm.
    let worst = assert_matches_truth(&rig, 100.0, &at_zero, &format!("{name} at 100 mm")).await;
    let s = rig.snapshot().await;
    let live = s.live.as_ref().expect("live");
    let expected = relative(&rig.twin.plant.truth(Instant::now()), &at_zero);
    eprintln!(
        "{name} at 100 mm: dy measured {:.3} µm, true {:.3} µm, stated sd {:.3} µm (stitching {:.3} µm); worst DOF {worst:.2} sd",
        live.errors[1], expected[1], live.sd[1], s.tracking.sd_um[0]
    );
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overlap_stitching_over_100_mm_matches_the_truth() {
    hundred_mm(Strategy::Overlap).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "continuous following needs cyclic synchronous position (CSP); profile position stalls on its set-point handshake"]
async fn encoder_tracking_over_100_mm_matches_the_truth() {
    hundred_mm(Strategy::Encoder).await;
}
