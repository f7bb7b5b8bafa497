//! The calibration hexapod: axiscomp's PI GCS and Newport XPS drivers against the twin's
//! controllers on loopback (both protocols over one platform), with the controller's faults.

use axiscomp::hexapod::driver::Timeouts;
use axiscomp::hexapod::{Driver, HexPose, Hexapod, HexapodError, Workspace};
use axiscomp::sim::hexapod_servers::{
    HexapodFault, HexapodMount, HexapodServers, TwinHexapodSpec, start,
};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

pub(crate) fn spec() -> TwinHexapodSpec {
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

pub(crate) async fn driver(s: &HexapodServers, kind: Driver) -> Hexapod {
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
        let t0 = axiscomp::util::clock::now();
        let reached = h.move_to(POSE).await.expect("move");
        // 2 mm at 50 mm/s: the move takes its time before "in position".
        assert!(
            axiscomp::util::clock::since(t0) >= Duration::from_millis(35),
            "{kind:?} {:?}",
            axiscomp::util::clock::since(t0)
        );
        assert!(close(&reached, &POSE, 1e-3), "{kind:?} reached {reached:?}");
        let platform = s.hexapod.mount.pose_at(axiscomp::util::clock::now());
        assert!(close(&platform, &reached, 1e-6), "{kind:?}");
        let again = h.position().await.expect("position");
        assert!(close(&again, &reached, 1e-6));
        assert_eq!(s.hexapod.moves(), 1);
    }
}

/// The speed setting reaches both controllers (GCS `VLS`, the HXP's actuator SGamma
/// velocity) and the platform moves at it: 4 mm at 8 mm/s takes half a second.
#[tokio::test]
async fn both_drivers_set_the_platforms_speed() {
    for kind in [Driver::PiGcs, Driver::NewportXps] {
        let s = servers().await;
        let mut h = driver(&s, kind).await;
        h.initialize().await.expect("initialise");
        h.set_speed(8.0).await.expect("speed");
        let t0 = axiscomp::util::clock::now();
        h.move_to(HexPose([0.0, 4.0, 0.0, 0.0, 0.0, 0.0]))
            .await
            .expect("move");
        let took = axiscomp::util::clock::since(t0);
        // At the twin's 50 mm/s it would take 80 ms.
        assert!(
            took >= Duration::from_millis(480) && took < Duration::from_secs(3),
            "{kind:?}: {took:?}"
        );
        // Beyond the controller's limit: refused with its code (GCS 17, XPS -17).
        let e = h.set_speed(500.0).await.expect_err("too fast");
        assert!(
            matches!(e, HexapodError::Controller { code, .. } if code.abs() == 17),
            "{kind:?}: {e}"
        );
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
        let y = s.hexapod.mount.pose_at(axiscomp::util::clock::now()).0[1];
        assert!(y > 0.1 && y < 1.5, "{kind:?}: halted at y = {y} mm ({r:?})");
    }
}

// ---------- the calibration procedure on the twin ----------

use crate::helpers::{TempDir, link_config};
use axiscomp::acquire::{AcquireConfig, Acquisition, IoMap};
use axiscomp::calibrate::CalibrateOptions;
use axiscomp::hexapod::bench::{Bench, Stay};
use axiscomp::hexapod::plan::{PlanError, PlanSpec, PosePlan};
use axiscomp::hexapod::procedure::{
    Judgement, PoseStore, ProcedureError, RunOptions, RunProgress, RunReport, fit_and_judge,
    never_stop, run,
};
use axiscomp::optics::Layout;
use axiscomp::sim::InstallSpec;
use axiscomp::sim::iomodule::IoModule;
use axiscomp::sim::plant::{Plant, PlantSpec};
use axiscomp::units::DOF_NAMES;

pub(crate) struct Rig {
    pub(crate) plant: Arc<Plant>,
    _io: IoModule,
    pub(crate) acq: Acquisition,
    pub(crate) servers: HexapodServers,
}

/// The twin's head with installation errors (±0.5 mm, ±0.2°, 1 % PSD gain) on the hexapod,
/// read through the I/O module over Modbus at 1 kHz.
pub(crate) async fn rig(seed: u64) -> Rig {
    let plant = Arc::new(
        Plant::new(
            &Layout::reference(),
            &PlantSpec {
                seed,
                install: InstallSpec {
                    offset_mm: 0.5,
                    tilt_deg: 0.2,
                    gain_error: 0.01,
                },
                ..PlantSpec::default()
            },
            axiscomp::util::clock::now(),
        )
        .expect("plant"),
    );
    let io = IoModule::generic(plant.clone()).await.expect("I/O module");
    let acq = Acquisition::spawn_paced(
        link_config(io.local_addr()),
        Arc::new(IoMap::generic().expect("map")),
        AcquireConfig {
            rate_hz: 1000.0,
            ..AcquireConfig::default()
        },
    );
    let servers = start(spec(), plant.hexapod.clone()).await.expect("hexapod");
    Rig {
        plant,
        _io: io,
        acq,
        servers,
    }
}

/// Run `plan` on the rig with quick settings (5 ms settle, 20 frames), the carriage and the
/// follower staying where they are.
async fn take(
    h: &mut Hexapod,
    r: &Rig,
    plan: &PosePlan,
    store: &mut PoseStore,
    on: &mut (dyn FnMut(&RunProgress) + Send),
) -> Result<RunReport, ProcedureError> {
    take_on(h, r, &mut Stay, plan, store, on).await
}

/// `take` with `bench` bringing the carriage and the follower to each station.
pub(crate) async fn take_on(
    h: &mut Hexapod,
    r: &Rig,
    bench: &mut impl Bench,
    plan: &PosePlan,
    store: &mut PoseStore,
    on: &mut (dyn FnMut(&RunProgress) + Send),
) -> Result<RunReport, ProcedureError> {
    let mut rx = r.acq.subscribe();
    let stop = never_stop();
    run(
        h,
        &mut rx,
        bench,
        plan,
        &spec().workspace,
        store,
        &quick(),
        &stop,
        on,
    )
    .await
}

/// Fit and judge `store` with the default options on the reference layout.
pub(crate) fn judge(store: &PoseStore) -> Result<Judgement, ProcedureError> {
    fit_and_judge(
        store,
        &Layout::reference(),
        &CalibrateOptions::default(),
        &mut |_, _| {},
    )
}

/// Every DOF's single-frame hold-out within `limit` × the Cramér–Rao bound.
pub(crate) fn assert_within(j: &Judgement, limit: f64) {
    let ratio = j.ratio();
    for k in 0..6 {
        assert!(
            ratio[k] <= limit,
            "{}: hold-out {:.3e} is {:.3}× the bound {:.3e}",
            DOF_NAMES[k],
            j.holdout_rms[k],
            ratio[k],
            j.crlb[k]
        );
    }
}

pub(crate) fn quick() -> RunOptions {
    RunOptions {
        settle: Duration::from_millis(5),
        frames: 20,
        ..RunOptions::default()
    }
}

/// The whole procedure on the twin through the XPS driver: every pose stored, the fitted
/// calibration within 1.15× the single-frame Cramér–Rao bound on every DOF on the held-out
/// poses, and the head at the calibrated pose reads what the hexapod says.
#[tokio::test(start_paused = true)]
async fn the_procedure_calibrates_the_twins_head() {
    let r = rig(5).await;
    let dir = TempDir::new("hexapod-proc");
    let plan = PosePlan::generate(&PlanSpec {
        poses: 120,
        ..PlanSpec::default()
    });
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("store");
    let mut h = driver(&r.servers, Driver::NewportXps).await;
    let mut seen = Vec::new();
    let report = take(&mut h, &r, &plan, &mut store, &mut |p| {
        seen.push((p.done, p.eta))
    })
    .await
    .expect("run");
    assert_eq!(report.taken, 120);
    assert_eq!(store.poses.len(), 120);
    assert_eq!(seen.len(), 120);
    assert!(seen[10].1.is_some_and(|eta| eta > Duration::ZERO));
    assert_eq!(seen.last().map(|s| s.1), Some(Some(Duration::ZERO)));
    // The last pose stood far out along y; after it the platform went back to its zero pose,
    // where the plant sees only the axis' own errors at D = 0 (tens of µm and arcsec at most).
    let truth = r
        .plant
        .truth(axiscomp::util::clock::now())
        .errors
        .to_array();
    let last = store.poses[119].reached.to_errors().to_array();
    assert!(last[1].abs() > 0.5, "a pose far out along y: {last:?}");
    for k in 0..6 {
        let tol = if k < 3 { 0.04 } else { 2e-4 };
        assert!(truth[k].abs() < tol, "not back at the zero pose: {truth:?}");
    }

    let j = judge(&store).expect("fit");
    assert_eq!(j.holdout_poses, 24);
    assert_eq!(j.frames, 24 * 20);
    assert_within(&j, 1.15);
    // The frame noise is the twin's 1 µm (plus the I/O module's quantisation).
    for s in j.sigma_frame_mm {
        assert!((0.9e-3..1.3e-3).contains(&s), "σ {s}");
    }
}

/// A controller error mid-plan stops the run with the controller's code and text, nothing
/// after it moves, and a second run resumes at the next pose; a dropped link is reconnected
/// and the pose taken again.
#[tokio::test(start_paused = true)]
async fn a_controller_error_stops_and_the_run_resumes_a_dropped_link_reconnects() {
    let r = rig(6).await;
    let dir = TempDir::new("hexapod-resume");
    let plan = PosePlan::generate(&PlanSpec {
        poses: 12,
        ..PlanSpec::default()
    });
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("store");
    let mut h = driver(&r.servers, Driver::PiGcs).await;
    let hx = r.servers.hexapod.clone();
    let e = take(&mut h, &r, &plan, &mut store, &mut |p| {
        if p.done == 5 {
            hx.inject(HexapodFault::Error(10));
        }
    })
    .await
    .expect_err("controller error");
    assert_eq!(
        e.to_string(),
        "pose 6 of 12: PI C-887 error 10: Controller was stopped by command; the poses taken so far are stored: run again to resume"
    );
    assert_eq!(store.poses.len(), 5);
    let moves = hx.moves();
    assert_eq!(moves, 6);

    // Resume from the files, as after a crash; the link drops at pose 8.
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("reopen");
    assert_eq!(store.next_index(), 5);
    let report = take(&mut h, &r, &plan, &mut store, &mut |p| {
        if p.done == 7 {
            hx.inject(HexapodFault::DropLink);
        }
    })
    .await
    .expect("resumed");
    assert_eq!(report.resumed_from, 5);
    assert_eq!(report.taken, 7);
    assert_eq!(report.reconnects, 1);
    let idx: Vec<usize> = store.poses.iter().map(|p| p.index).collect();
    assert_eq!(idx, (1..=12).collect::<Vec<_>>());
    let again = PoseStore::open(&dir.path("run"), &plan).expect("reopen");
    assert_eq!(again.poses.len(), 12);
    assert_eq!(again.frames().expect("frames").len(), 12 * 20);

    // Another plan is not resumed into this run.
    let other = PosePlan::generate(&PlanSpec {
        poses: 13,
        ..PlanSpec::default()
    });
    let e = PoseStore::open(&dir.path("run"), &other)
        .err()
        .expect("refused");
    assert!(e.to_string().contains("another plan"), "{e}");
}

/// A plan pose outside the workspace is refused before any move.
#[tokio::test(start_paused = true)]
async fn a_plan_outside_the_workspace_is_refused_before_any_move() {
    let r = rig(7).await;
    let dir = TempDir::new("hexapod-ws");
    let mut plan = PosePlan::generate(&PlanSpec {
        poses: 10,
        ..PlanSpec::default()
    });
    plan.poses[6].pose.0[2] = 6.5;
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("store");
    let mut h = driver(&r.servers, Driver::PiGcs).await;
    let e = take(&mut h, &r, &plan, &mut store, &mut |_| {})
        .await
        .expect_err("outside");
    match &e {
        ProcedureError::Plan(PlanError::OutsideWorkspace {
            index, axis, value, ..
        }) => {
            assert_eq!((*index, *axis, *value), (7, "Z", 6.5));
        }
        other => panic!("{other}"),
    }
    assert_eq!(r.servers.hexapod.moves(), 0);
    assert!(store.poses.is_empty());
}

// ---------- the command line ----------

use crate::helpers::{run as run_bin, stderr};

/// `axiscomp calibrate run` refuses a plan pose outside `[hexapod] workspace`, and a plan at
/// several positions, before it connects to anything, and `axiscomp check` names a bad
/// `[hexapod]` key.
#[test]
fn the_command_line_checks_plan_and_config_first() {
    let dir = TempDir::new("hexapod-cli");
    let cfg = dir.write(
        "svc.toml",
        "[hexapod]\ndriver = \"newport-xps\"\naddress = \"127.0.0.1:9\"\nworkspace = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]\n",
    );
    let out = dir.path("run");
    // `calibrate run` with `plan` (CSV text): refused with `refusal`, nothing stored.
    let refused = |name: &str, plan: &str, refusal: &str| {
        let plan = dir.write(name, plan);
        let o = run_bin(
            &[
                "calibrate",
                "run",
                "--config",
                cfg.to_str().unwrap(),
                "--plan",
                plan.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ],
            "",
        );
        assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
        assert!(stderr(&o).contains(refusal), "{}", stderr(&o));
        assert!(!out.exists(), "nothing stored");
    };
    refused(
        "plan.csv",
        "x_mm,y_mm,z_mm,u_deg,v_deg,w_deg\n0,0,0,0,0,0\n0,1.5,0,0,0,0\n",
        "pose 2 of the plan: Y = 1.5 is outside the hexapod's workspace (-1 to 1); no pose was moved to",
    );
    // A plan at two positions: the command line moves neither the carriage nor the follower.
    refused(
        "along.csv",
        "x_mm,y_mm,z_mm,u_deg,v_deg,w_deg,travel_mm,follower_mm\n0,0,0,0,0,0,0,0\n0,0.5,0,0,0,0,100,100\n",
        "pose 2 of the plan is at travel 100 mm with the follower at 100 mm, pose 1 at 0 mm and 0 mm: nothing here moves the carriage and the follower (the service does, with [cnc] mode = \"twin\")",
    );

    let bad = dir.write("bad.toml", "[hexapod]\ndriver = \"hxp\"\n");
    let o = run_bin(&["check", "--config", bad.to_str().unwrap()], "");
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o).contains("hexapod.driver: \"hxp\": use \"pi-gcs\""),
        "{}",
        stderr(&o)
    );
    let o = run_bin(&["check", "--config", "configs/twin-service.toml"], "");
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
}

/// A following error mid-plan (Newport): the run stops with -25 and the controller's text;
/// the resumed run initialises the disabled group again and finishes.
#[tokio::test(start_paused = true)]
async fn a_following_error_stops_and_the_resumed_run_initialises_again() {
    let r = rig(8).await;
    let dir = TempDir::new("hexapod-following");
    let plan = PosePlan::generate(&PlanSpec {
        poses: 8,
        ..PlanSpec::default()
    });
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("store");
    let mut h = driver(&r.servers, Driver::NewportXps).await;
    let hx = r.servers.hexapod.clone();
    let e = take(&mut h, &r, &plan, &mut store, &mut |p| {
        if p.done == 3 {
            hx.inject(HexapodFault::FollowingError);
        }
    })
    .await
    .expect_err("following error");
    assert_eq!(
        e.to_string(),
        "pose 4 of 8: Newport HXP error -25: Following Error; the poses taken so far are stored: run again to resume"
    );
    let report = take(&mut h, &r, &plan, &mut store, &mut |_| {})
        .await
        .expect("resumed");
    assert_eq!((report.resumed_from, report.taken), (3, 5));
    assert_eq!(store.poses.len(), 8);
}
