//! The calibration hexapod: axiscomp's PI GCS and Newport XPS drivers against the twin's
//! controllers on loopback (both protocols over one platform), with the controller's faults.

use axiscomp::hexapod::driver::Timeouts;
use axiscomp::hexapod::{Driver, HexPose, Hexapod, HexapodError, Workspace};
use axiscomp::sim::hexapod_servers::{
    HexapodFault, HexapodMount, HexapodServers, TwinHexapodSpec, start,
};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn spec() -> TwinHexapodSpec {
    TwinHexapodSpec {
        gcs: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
        xps: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
        workspace: Workspace::symmetric([5.0, 5.0, 5.0, 1.0, 1.0, 1.0]),
        speed_mm_s: 50.0,
        speed_deg_s: 10.0,
        ..TwinHexapodSpec::default()
    }
}

async fn servers() -> HexapodServers {
    start(spec(), Arc::new(HexapodMount::default()))
        .await
        .expect("twin hexapod")
}

async fn driver(s: &HexapodServers, kind: Driver) -> Hexapod {
    let addr = match kind {
        Driver::PiGcs => s.gcs,
        Driver::NewportXps => s.xps,
    }
    .expect("server");
    Hexapod::connect(kind, &addr.to_string(), "HEXAPOD", Timeouts::default())
        .await
        .expect("connect")
}

const POSE: HexPose = HexPose([0.1, -2.0, 0.05, 0.0166, -0.01, 0.02]);

fn close(a: &HexPose, b: &HexPose, tol: f64) -> bool {
    (0..6).all(|k| (a.0[k] - b.0[k]).abs() <= tol)
}

/// Each driver initialises, sets the pivot and work frame, moves and reads the reached pose;
/// the twin's platform (what the head sees) is there, within its repeatability.
#[tokio::test]
async fn both_drivers_move_the_twin_platform() {
    for kind in [Driver::PiGcs, Driver::NewportXps] {
        let s = servers().await;
        let mut h = driver(&s, kind).await;
        let id = h.identify().await.expect("identify");
        assert!(id.contains("twin"), "{id}");
        assert!(
            !h.referenced().await.expect("status"),
            "{kind:?} starts unreferenced"
        );
        h.initialize().await.expect("initialise");
        assert!(h.referenced().await.expect("status"));
        h.set_frames([0.0, 0.0, 120.5], HexPose([0.0, 0.0, 0.0, 0.0, 0.0, 90.0]))
            .await
            .expect("frames");
        let (pivot, work) = s.hexapod.frames();
        assert_eq!(pivot, [0.0, 0.0, 120.5]);
        assert_eq!(work.0[5], 90.0);
        let t0 = Instant::now();
        let reached = h.move_to(POSE).await.expect("move");
        // 2 mm at 50 mm/s: the move takes its time before "in position".
        assert!(
            t0.elapsed() >= Duration::from_millis(35),
            "{kind:?} {:?}",
            t0.elapsed()
        );
        assert!(close(&reached, &POSE, 1e-3), "{kind:?} reached {reached:?}");
        let platform = s.hexapod.mount.pose_at(Instant::now());
        assert!(close(&platform, &reached, 1e-6), "{kind:?}");
        let again = h.position().await.expect("position");
        assert!(close(&again, &reached, 1e-6));
        assert_eq!(s.hexapod.moves(), 1);
    }
}

/// A pose outside the workspace is refused by the controller with its code and text
/// (GCS 7, XPS -17) and nothing moves.
#[tokio::test]
async fn the_controllers_refuse_a_pose_outside_their_workspace() {
    for (kind, code, text) in [
        (Driver::PiGcs, 7, "Position out of limits"),
        (Driver::NewportXps, -17, "Parameter out of range"),
    ] {
        let s = servers().await;
        let mut h = driver(&s, kind).await;
        h.initialize().await.expect("initialise");
        let e = h
            .move_to(HexPose([6.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
            .await
            .expect_err("outside");
        assert_eq!(
            e,
            HexapodError::Controller {
                controller: kind.name(),
                code,
                text: text.into()
            }
        );
        assert!(close(
            &h.position().await.expect("pos"),
            &HexPose::default(),
            1e-3
        ));
    }
}

/// Faults: a controller error code, a following error (the servo drops; initialising again
/// clears it), and a dropped link (reconnect, and the platform is still there).
#[tokio::test]
async fn faults_carry_the_controllers_code_and_the_link_reconnects() {
    for (kind, following) in [(Driver::PiGcs, -1024), (Driver::NewportXps, -25)] {
        let s = servers().await;
        let mut h = driver(&s, kind).await;
        h.initialize().await.expect("initialise");

        let code = if kind == Driver::PiGcs { 10 } else { -26 };
        s.hexapod.inject(HexapodFault::Error(code));
        match h.move_to(POSE).await {
            Err(HexapodError::Controller { code: c, text, .. }) => {
                assert_eq!(c, code);
                let want = if kind == Driver::PiGcs {
                    "Controller was stopped by command"
                } else {
                    "Emergency signal"
                };
                assert_eq!(text, want);
            }
            other => panic!("{kind:?}: {other:?}"),
        }

        s.hexapod.inject(HexapodFault::FollowingError);
        match h.move_to(POSE).await {
            Err(HexapodError::Controller { code, text, .. }) => {
                assert_eq!(code, following, "{kind:?}");
                assert!(
                    text.contains("ollowing") || text.contains("position error too large"),
                    "{text}"
                );
            }
            other => panic!("{kind:?}: {other:?}"),
        }
        // Servo off / group disabled: moving needs initialising again.
        assert!(h.move_to(POSE).await.is_err());
        h.initialize().await.expect("initialise after the fault");
        h.move_to(POSE).await.expect("move after re-initialising");

        s.hexapod.inject(HexapodFault::DropLink);
        let e = h.move_to(HexPose::default()).await.expect_err("dropped");
        assert!(e.is_link(), "{kind:?}: {e}");
        assert!(!h.connected());
        assert!(h.position().await.expect_err("not connected").is_link());
        h.reconnect().await.expect("reconnect");
        let p = h.position().await.expect("position after reconnecting");
        assert!(close(&p, &POSE, 1e-3), "{kind:?}: {p:?}");
        h.move_to(HexPose::default())
            .await
            .expect("move after reconnecting");
    }
}

/// A stop during a move: the platform halts short of the target.
#[tokio::test]
async fn stop_halts_a_move() {
    for kind in [Driver::PiGcs, Driver::NewportXps] {
        let mut sp = spec();
        sp.speed_mm_s = 2.0;
        let s = start(sp, Arc::new(HexapodMount::default()))
            .await
            .expect("twin");
        let mut h = driver(&s, kind).await;
        h.initialize().await.expect("initialise");
        let mut stopper = driver(&s, kind).await;
        let target = HexPose([0.0, 2.0, 0.0, 0.0, 0.0, 0.0]);
        let mover = tokio::spawn(async move { h.move_to(target).await });
        tokio::time::sleep(Duration::from_millis(200)).await;
        stopper.stop().await.expect("stop");
        let r = mover.await.expect("join");
        let y = s.hexapod.mount.pose_at(Instant::now()).0[1];
        assert!(y > 0.1 && y < 1.5, "{kind:?}: halted at y = {y} mm ({r:?})");
    }
}
