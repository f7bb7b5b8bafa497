//! The follower's stop-and-go mapping through the service against the twin (issue 14): the
//! twin's certificate imported through the control API, the mapping started there over a
//! short span, its part program run by the twin's CNC, the map built, stored with the
//! certificate and in use; its vertical against the twin's true follower vertical within the
//! map's stated uncertainty. Refusals both ways with a measurement run and a hexapod run, a
//! bad certificate naming its line, an interrupted mapping said so at the next start.

use crate::helpers::{RigOptions, ServiceRig, TempDir, short_plan};
use axiscomp::follower::Source;
use axiscomp::service::api::CertificateImport;
use axiscomp::service::api::MappingRequest;
use axiscomp::service::api::Request;
use axiscomp::service::procedure::follower_map::{FollowerMapping, MappingConfig};
use std::time::Duration;

/// The twin's head square, the pre-run alignment check off (runs start at once).
const SERVICE: &str = "[align]\ncheck_before_run = false\n";

fn short_mapping() -> MappingRequest {
    MappingRequest {
        from_mm: Some(0.0),
        to_mm: Some(40.0),
        passes: Some(1),
        probe_every: Some(4),
        frames: Some(200),
        ..MappingRequest::default()
    }
}

/// A rig whose service reads the twin's level and sends programs to the twin's CNC.
async fn level_rig() -> ServiceRig {
    ServiceRig::start(RigOptions {
        service_toml: SERVICE.into(),
        follower_toml: Some("level = \"twin\"\n".into()),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await
}

/// The twin's certificate (its noise drawn from seed 5) imported through the control API.
async fn import_twin_certificate(rig: &ServiceRig) {
    let cert_text = rig
        .twin
        .plant
        .follower
        .certificate(&mut axiscomp::sim::Rng::new(5));
    rig.request(Request::FollowerCertificate(CertificateImport {
        csv: Some(cert_text),
        name: Some("twin-stage.csv".into()),
        ..CertificateImport::default()
    }))
    .await
    .expect("certificate import");
}

/// The short mapping run through the control API to its end: the map stored, its id.
async fn map_short(rig: &ServiceRig) -> i64 {
    rig.request(Request::FollowerMapStart(short_mapping()))
        .await
        .expect("mapping start");
    let s = rig
        .wait_for(180, "the mapping done", |s| {
            s.follower_mapping.as_ref().is_some_and(|m| !m.active())
        })
        .await;
    let m = s.follower_mapping.expect("the mapping's view");
    assert_eq!(m.state, "done", "{m:#?}");
    m.map_id.expect("the mapping's map")
}

/// Over 40 mm (one pass up, a probe every four stops: 14 stops of 200 frames a side), through
/// the control API: the map is stored with the twin's certificate, in use and in the
/// snapshot; its vertical is the twin's true follower vertical (to the end-point line over
/// the mapped span) within 3 u at every point.
#[tokio::test(start_paused = true)]
async fn the_service_maps_the_twins_follower_through_the_control_api() {
    let wall = std::time::Instant::now();
    let rig = ServiceRig::start(RigOptions {
        service_toml: SERVICE.into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    // A bad certificate through the API: refused naming its line, nothing stored.
    let e = rig
        .request(Request::FollowerCertificate(CertificateImport {
            csv: Some(
                "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n10,1,,0.2\n".into(),
            ),
            name: Some("bad.csv".into()),
            ..CertificateImport::default()
        }))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("bad.csv line 3, column direction: empty field"),
        "{e}"
    );
    let e = rig
        .request(Request::FollowerCertificate(CertificateImport {
            path: Some("/nonexistent/stage.csv".into()),
            ..CertificateImport::default()
        }))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("certificate /nonexistent/stage.csv: cannot read it"),
        "{e}"
    );
    // The twin's own certificate, imported through the service: in use at once.
    let cert_text = rig
        .twin
        .plant
        .follower
        .certificate(&mut axiscomp::sim::Rng::new(5));
    let r = rig
        .request(Request::FollowerCertificate(CertificateImport {
            csv: Some(cert_text),
            name: Some("twin-stage.csv".into()),
            ..CertificateImport::default()
        }))
        .await
        .expect("certificate import");
    assert_eq!(r["in_use"], true, "{r}");
    let cert_id = r["id"].as_i64().expect("id");
    rig.wait_for(10, "the certificate's map in the snapshot", |s| {
        s.tracking.follower_map.as_ref().map(|m| m.id) == Some(cert_id)
    })
    .await;
    // The mapping, started through the control API.
    let started = rig
        .request(Request::FollowerMapStart(short_mapping()))
        .await
        .expect("mapping start");
    eprintln!("{}", serde_json::to_string_pretty(&started).unwrap());
    assert_eq!(started["stops_planned"], 14, "{started}");
    // 2.1 s at the configured 500 Hz; longer when the frames come slower now (a loaded host).
    let dwell = started["dwell_s"].as_f64().expect("dwell");
    assert!(dwell >= 2.1, "{started}");
    assert!(
        started["certificate"]
            .as_str()
            .is_some_and(|c| c.starts_with("twin-stage.csv")),
        "{started}"
    );
    let program = std::fs::read_to_string(started["program"].as_str().expect("program"))
        .expect("the program in the state directory");
    let g04 = format!("G04 P{:.0}", dwell * 1000.0);
    assert_eq!(program.matches(&g04).count(), 16, "{program}");
    // Under way: a run and a hexapod run are refused, naming the mapping and how to end it.
    let e = rig
        .request(Request::RunStart {
            plan: short_plan(),
            dialect: None,
            notes: None,
        })
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("the follower mapping is under way") && e.contains("follower_map_stop"),
        "{e}"
    );
    let e = rig
        .request(Request::HexapodStart {
            plan: None,
            poses: None,
            out: None,
        })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("the follower mapping is under way"), "{e}");
    let e = rig
        .request(Request::FollowerMapStart(short_mapping()))
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("a follower mapping is under way"), "{e}");
    // Progress in the snapshot, then done.
    let mut seen_mapping = false;
    let s = rig
        .wait_for(180, "the mapping done", |s| {
            let m = s.follower_mapping.as_ref();
            seen_mapping |= m.is_some_and(|m| m.state == "mapping" && m.stops_done > 0);
            m.is_some_and(|m| !m.active())
        })
        .await;
    let m = s.follower_mapping.clone().expect("the mapping's view");
    assert!(seen_mapping, "progress was never shown");
    assert_eq!(m.state, "done", "{m:#?}");
    let status = rig
        .request(Request::FollowerMapStatus)
        .await
        .expect("status");
    eprintln!("{}", serde_json::to_string_pretty(&status).unwrap());
    assert_eq!(
        (m.stops_done, m.stops_planned, m.out_of_plan),
        (14, 14, 0),
        "{m:#?}"
    );
    assert!(m.steps_kept >= 12, "{m:#?}");
    let id = m.map_id.expect("the map stored");
    assert!(
        m.summary
            .iter()
            .any(|l| l.starts_with("vertical straightness")),
        "{m:#?}"
    );
    // In use, in the snapshot, with the certificate kept.
    let s = rig
        .wait_for(10, "the new map in the snapshot", |s| {
            s.tracking.follower_map.as_ref().map(|v| v.id) == Some(id)
        })
        .await;
    let v = s.tracking.follower_map.expect("map view");
    assert_eq!(v.source, "both");
    let rec = {
        let store = axiscomp::store::Store::open_read_only(&rig.store).expect("store");
        store.follower_map(id).expect("stored map")
    };
    assert!(rec.in_use);
    assert_eq!(
        rec.certificate.as_ref().map(|c| c.name.as_str()),
        Some("twin-stage.csv")
    );
    let map = &rec.map;
    assert_eq!(map.sources.long, Source::Certificate);
    assert_eq!(map.sources.vertical, Source::SelfCalibration);
    let machine_s = map
        .self_calibration
        .and_then(|s| s.machine_time_s)
        .expect("machine time");
    // The vertical against the twin's truth, both to their end-point lines.
    let truth = &rig.twin.plant.follower;
    let vp = &map.vertical_positions_mm;
    let (x0, x1) = (vp[0], vp[vp.len() - 1]);
    let line = |x: f64| {
        truth.vertical(x0) + (truth.vertical(x1) - truth.vertical(x0)) * (x - x0) / (x1 - x0)
    };
    let (mut worst_u, mut worst_um, mut max_u) = (0.0f64, 0.0f64, 0.0f64);
    for (i, &x) in vp.iter().enumerate() {
        let err = (map.vertical_mm[i] - (truth.vertical(x) - line(x))) * 1e3;
        let u = map.vertical_u_mm[i] * 1e3;
        eprintln!("  vertical at {x:7.2} mm: map − truth {err:+.3} µm, u {u:.3} µm");
        worst_um = worst_um.max(err.abs());
        max_u = max_u.max(u);
        if u > 0.0 {
            worst_u = worst_u.max(err.abs() / u);
        }
        assert!(
            err.abs() <= 3.0 * u + 0.01,
            "vertical at {x:.2} mm: map − truth {err:.3} µm, u {u:.3} µm"
        );
    }
    eprintln!(
        "service-mapped {x0:.1}–{x1:.1} mm: {} points, worst |map − truth| {worst_um:.3} µm = {worst_u:.2} u (largest u {max_u:.3} µm); {:.1} s of machine time, {:.1} s of wall time so far",
        vp.len(),
        machine_s,
        wall.elapsed().as_secs_f64()
    );
    // A run under way refuses the mapping, naming the run and how to end it.
    let r = rig
        .request(Request::RunStart {
            plan: short_plan(),
            dialect: None,
            notes: None,
        })
        .await
        .expect("run start");
    let run_id = r["run_id"].as_i64().expect("run id");
    let e = rig
        .request(Request::FollowerMapStart(short_mapping()))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!("measurement run {run_id} is under way")) && e.contains("run_abort"),
        "{e}"
    );
    rig.request(Request::RunAbort).await.expect("abort");
    // Stopped: nothing stored, the map in use unchanged.
    rig.request(Request::FollowerMapStart(short_mapping()))
        .await
        .expect("a second mapping");
    let v = rig.request(Request::FollowerMapStop).await.expect("stop");
    assert_eq!(v["state"], "stopped", "{v}");
    assert!(
        v["error"]
            .as_str()
            .is_some_and(|e| e.contains("no map was stored")),
        "{v}"
    );
    let s = rig.snapshot().await;
    assert_eq!(s.tracking.follower_map.map(|m| m.id), Some(id));
    assert_eq!(s.tracking.strategy, "overlap");
    rig.stop().await;
    eprintln!(
        "wall time of the test: {:.1} s",
        wall.elapsed().as_secs_f64()
    );
}

/// A mapping the service did not finish (a restart) is said to be interrupted at the next
/// start: no map, the marker gone.
#[test]
fn a_mapping_interrupted_by_a_restart_is_said_so() {
    let dir = TempDir::new("mapping-interrupted");
    let state = dir.path("state");
    std::fs::create_dir_all(&state).unwrap();
    std::fs::write(
        state.join("follower-mapping.json"),
        r#"{"axis":"X","from_mm":0.0,"to_mm":400.0,"started":"2026-11-20T08:15:00Z","started_by":"op"}"#,
    )
    .unwrap();
    let cfg = MappingConfig {
        cnc: axiscomp::config::CncMode::Manual,
        dialect: axiscomp::run::Dialect::Iso,
        state_dir: state.clone(),
        frame_rate_hz: 500.0,
        follower_velocity_mm_s: 200.0,
        follower_accel_mm_s2: 5000.0,
        sync: Duration::from_millis(10),
    };
    let m = FollowerMapping::new(cfg.clone());
    let v = m.view().expect("a view");
    assert_eq!(v.state, "interrupted");
    assert_eq!(
        v.error.as_deref(),
        Some(
            "the follower mapping over X 0.0 to 400.0 mm started 2026-11-20T08:15:00Z by op was interrupted by a service restart: its steps are lost, no map was stored and the map in use is unchanged; stop its part program on the CNC if it still runs, then start the mapping again"
        )
    );
    assert!(!m.active());
    assert!(!state.join("follower-mapping.json").exists());
    // Once said, the next start is a clean one.
    assert!(FollowerMapping::new(cfg).view().is_none());
}

/// `axiscomp follower import|map` on the command line: the certificate through the running
/// service (applied at once) and into the store when no service answers; the mapping started
/// detached, its status, stopped.
#[tokio::test(start_paused = true)]
async fn the_command_line_imports_and_maps_through_the_service() {
    use crate::helpers::{run, stderr, stdout};
    let rig = ServiceRig::start(RigOptions {
        service_toml: SERVICE.into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    let dir = TempDir::new("follower-cli-service");
    let cert = dir.write(
        "stage.csv",
        "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n20,1.0,+,0.2\n40,2.0,+,0.2\n",
    );
    let sock = rig.socket.display().to_string();
    let cli = |args: Vec<String>| {
        tokio::task::spawn_blocking(move || {
            let a: Vec<&str> = args.iter().map(String::as_str).collect();
            run(&a, "")
        })
    };
    let args = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let o = cli(args(&[
        "follower",
        "import",
        &cert.display().to_string(),
        "--socket",
        &sock,
    ]))
    .await
    .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(
        out.contains(&format!("stored by the running service ({sock})"))
            && out.contains("take the zero again"),
        "{out}"
    );
    rig.wait_for(10, "the certificate's map in use", |s| {
        s.tracking
            .follower_map
            .as_ref()
            .is_some_and(|m| m.source == "certificate")
    })
    .await;
    // No service at the socket: the store directly, said so.
    let cfg = dir.write(
        "axiscomp.toml",
        &format!(
            "[service]\nstate_dir = \"{}\"\n",
            dir.path("state").display()
        ),
    );
    std::fs::create_dir_all(dir.path("state")).unwrap();
    let none = dir.path("none.sock").display().to_string();
    let o = cli(args(&[
        "follower",
        "import",
        &cert.display().to_string(),
        "--socket",
        &none,
        "--config",
        &cfg.display().to_string(),
    ]))
    .await
    .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(
        out.contains(&format!(
            "no service answers at {none}: the certificate goes into the store directly"
        )) && out.contains("in use from the service's next start"),
        "{out}"
    );
    // A start refused (a span too short for the fit): the status says so, with the reason
    // (it said only that no mapping ran since the service started).
    let o = cli(args(&[
        "follower",
        "map",
        "--socket",
        &sock,
        "--from-mm",
        "0",
        "--to-mm",
        "5",
    ]))
    .await
    .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let why = stderr(&o);
    let o = cli(args(&["follower", "map", "--status", "--socket", &sock]))
        .await
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let out = stdout(&o);
    let reason = why.trim().strip_prefix("axiscomp: ").unwrap_or_default();
    assert!(
        out.contains("no follower mapping since the service started; the last start, at 20")
            && out.contains(" UTC, was refused: ")
            && !reason.is_empty()
            && out.contains(reason.lines().next().unwrap_or_default()),
        "status:\n{out}\nthe refusal:\n{why}"
    );
    // The mapping, detached; its status; stopped.
    let o = cli(args(&[
        "follower",
        "map",
        "--socket",
        &sock,
        "--from-mm",
        "0",
        "--to-mm",
        "40",
        "--passes",
        "1",
        "--probe-every",
        "4",
        "--frames",
        "200",
        "--detach",
    ]))
    .await
    .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(
        out.contains("follower mapping approaching: stop 0 of 14")
            && out.contains(" s at each stop: rest detection 0.30 s")
            && out.contains("follow it with: axiscomp follower map --status"),
        "{out}"
    );
    let o = cli(args(&["follower", "map", "--status", "--socket", &sock]))
        .await
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(stdout(&o).contains(" of 14, "), "{}", stdout(&o));
    // A second start is refused: input to fix, exit 2.
    let o = cli(args(&[
        "follower",
        "map",
        "--socket",
        &sock,
        "--from-mm",
        "0",
        "--to-mm",
        "40",
    ]))
    .await
    .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("a follower mapping is under way"),
        "{}",
        stderr(&o)
    );
    let o = cli(args(&["follower", "map", "--stop", "--socket", &sock]))
        .await
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("follower mapping stopped:")
            && stdout(&o).contains("no map was stored"),
        "{}",
        stdout(&o)
    );
    // Followed on the command line, Ctrl-C leaves the mapping running in the service and says
    // so, with how to follow and stop it (it ended the command without a word).
    let sock2 = sock.clone();
    let o = tokio::task::spawn_blocking(move || {
        use std::io::BufRead;
        let mut child = crate::helpers::bin()
            .args([
                "follower",
                "map",
                "--socket",
                &sock2,
                "--from-mm",
                "0",
                "--to-mm",
                "40",
            ])
            .args(["--passes", "1", "--probe-every", "4", "--frames", "200"])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("spawn axiscomp");
        // Its first line is the started mapping's status: it follows from then on.
        let mut out = std::io::BufReader::new(child.stdout.take().expect("stdout"));
        let mut first = String::new();
        out.read_line(&mut first).expect("first line");
        // SAFETY: kill(2) on our own child's pid, which it keeps until we wait for it.
        let sent = unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGINT) };
        assert_eq!(sent, 0, "SIGINT");
        let o = child.wait_with_output().expect("wait axiscomp");
        (first, o)
    })
    .await
    .unwrap();
    let (first, o) = o;
    assert!(first.contains("follower mapping approaching"), "{first}");
    assert_eq!(o.status.code(), Some(130), "{}", stderr(&o));
    assert!(
        stderr(&o).contains(
            "axiscomp: Ctrl-C: the follower mapping goes on in the service; follow it with: \
             axiscomp follower map --status; stop it with: axiscomp follower map --stop"
        ),
        "{}",
        stderr(&o)
    );
    let o = cli(args(&["follower", "map", "--status", "--socket", &sock]))
        .await
        .unwrap();
    assert!(
        stdout(&o).contains(" of 14, "),
        "still running: {}",
        stdout(&o)
    );
    let o = cli(args(&["follower", "map", "--stop", "--socket", &sock]))
        .await
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    rig.stop().await;
}

/// With a CNC the service does not drive (`[cnc] mode = "manual"`): the program is written for
/// the operator, the carriage goes through its stops (here the test is the CNC), the mapping
/// ends by itself once every planned stop was seen; `follower_map_finish` with no steps fails
/// in words and leaves the map in use.
#[tokio::test(start_paused = true)]
async fn with_a_manual_cnc_the_mapping_ends_when_every_stop_was_seen() {
    use axiscomp::follower::selfcal::{Plan, Spec};
    let rig = ServiceRig::start(RigOptions {
        service_toml: SERVICE.into(),
        ..RigOptions::default()
    })
    .await;
    let req = MappingRequest {
        from_mm: Some(0.0),
        to_mm: Some(15.0),
        passes: Some(3),
        probe_every: Some(0),
        frames: Some(100),
        dialect: Some("heidenhain".into()),
        ..MappingRequest::default()
    };
    let v = rig
        .request(Request::FollowerMapStart(req))
        .await
        .expect("start");
    assert_eq!(v["cnc"], "load the program on the CNC and start it", "{v}");
    assert_eq!(v["stops_planned"].as_u64(), Some(12), "{v}");
    // 1.6 s at the configured 500 Hz; longer when the frames come slower now.
    let dwell = v["dwell_s"].as_f64().expect("dwell");
    assert!(dwell >= 1.6, "{v}");
    let program = std::fs::read_to_string(v["program"].as_str().unwrap()).unwrap();
    let cycl = format!("CYCL DEF 9.1 DWELL {dwell:.3}");
    assert!(
        program.starts_with("0 BEGIN PGM AXISCOMP MM\n") && program.matches(&cycl).count() == 14,
        "{program}"
    );
    // The operator's CNC: the lead-in, the start, then every stop with its dwell.
    let plan = Plan::new(Spec {
        from_mm: 0.0,
        to_mm: 15.0,
        step_mm: 3.75,
        passes: 3,
        probe_every: 0,
    })
    .unwrap();
    for x in plan.positions() {
        rig.twin.move_and_wait(x).await;
        tokio::time::sleep(Duration::from_secs_f64(dwell)).await;
    }
    let s = rig
        .wait_for(20, "the mapping ended", |s| {
            s.follower_mapping.as_ref().is_some_and(|m| !m.active())
        })
        .await;
    let m = s.follower_mapping.expect("view");
    eprintln!("{m:#?}");
    assert_eq!(m.state, "done", "{m:#?}");
    assert_eq!((m.stops_done, m.out_of_plan), (12, 0), "{m:#?}");
    let id = m.map_id.expect("map");
    // Finished by hand before any stop: no steps, no map, the map in use kept.
    rig.request(Request::FollowerMapStart(MappingRequest {
        from_mm: Some(0.0),
        to_mm: Some(15.0),
        passes: Some(3),
        ..MappingRequest::default()
    }))
    .await
    .expect("start again");
    let e = rig
        .request(Request::FollowerMapFinish)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("finished by root, but no map was built")
            && e.contains("the map in use is unchanged"),
        "{e}"
    );
    let s = rig
        .wait_for(10, "the failure in the snapshot", |s| {
            s.follower_mapping
                .as_ref()
                .is_some_and(|m| m.state == "failed")
        })
        .await;
    assert_eq!(s.tracking.follower_map.map(|m| m.id), Some(id));
    assert!(
        s.alarms
            .iter()
            .any(|a| a.code == "mapping-failed" && a.active),
        "{:?}",
        s.alarms
    );
    rig.stop().await;
}

/// The level's stations through the service on the twin (`[follower] level = "twin"`): the
/// follower mapped over 40 mm, then a station every 10 mm read by the twin's level beside the
/// head, the map fitted again with the stored steps and the stations, stored as a new map and
/// put in use. Its vertical, relative to its first point, against the twin's true follower
/// vertical relative to the same point, judged by its u as `follower.rs::check_map` judges the
/// lab's maps: the RMS of (map − truth)/u at most 2 and no point beyond 5 u (the points are
/// one correlated curve, all sharing the first station's error). Refusals both ways with a
/// measurement run, a hexapod run and the mapping while the stations are under way.
#[tokio::test(start_paused = true)]
async fn the_service_reads_the_twins_level_at_stations_and_refits_the_map() {
    use axiscomp::service::api::LevelRequest;
    let wall = std::time::Instant::now();
    let rig = level_rig().await;
    // Before any map with steps: refused in words.
    let e = rig
        .request(Request::FollowerLevelStart(LevelRequest::default()))
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("map the follower first"), "{e}");
    import_twin_certificate(&rig).await;
    let mapped = map_short(&rig).await;
    let mapped_at = wall.elapsed().as_secs_f64();
    // The stations: every 10 mm over the map's span.
    let req = LevelRequest {
        station_mm: Some(10.0),
        readings: Some(10),
        ..LevelRequest::default()
    };
    let v = rig
        .request(Request::FollowerLevelStart(req.clone()))
        .await
        .expect("level start");
    eprintln!("{}", serde_json::to_string_pretty(&v).unwrap());
    assert_eq!(v["state"], "stations", "{v}");
    assert_eq!(v["map_from"].as_i64(), Some(mapped), "{v}");
    let planned = v["stations"].as_array().map_or(0, Vec::len);
    assert!(planned >= 4, "{v}");
    // Under way: the others refused, naming the stations and how to end them; a typed
    // reading refused (the twin's level is read by the service).
    for (r, what) in [
        (
            Request::RunStart {
                plan: short_plan(),
                dialect: None,
                notes: None,
            },
            "run",
        ),
        (
            Request::HexapodStart {
                plan: None,
                poses: None,
                out: None,
            },
            "hexapod",
        ),
        (Request::FollowerMapStart(short_mapping()), "mapping"),
    ] {
        let e = rig.request(r).await.unwrap_err().to_string();
        assert!(
            e.contains("the follower's level stations are under way")
                && e.contains("follower_level_stop"),
            "{what}: {e}"
        );
    }
    let e = rig
        .request(Request::FollowerLevelStart(req))
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("level stations are under way"), "{e}");
    let e = rig
        .request(Request::FollowerLevelReading {
            arcsec: serde_json::json!(1.5),
        })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("the level is the twin's"), "{e}");
    let s = rig
        .wait_for(180, "the level stations done", |s| {
            s.follower_level.as_ref().is_some_and(|l| !l.active())
        })
        .await;
    let l = s.follower_level.expect("the stations' view");
    let status = rig
        .request(Request::FollowerLevelStatus)
        .await
        .expect("status");
    eprintln!("{}", serde_json::to_string_pretty(&status).unwrap());
    assert_eq!(l.state, "done", "{l:#?}");
    assert_eq!(l.taken, planned, "{l:#?}");
    let id = l.map_id.expect("the map stored");
    assert_ne!(id, mapped);
    rig.wait_for(10, "the refitted map in the snapshot", |s| {
        s.tracking.follower_map.as_ref().map(|v| v.id) == Some(id)
    })
    .await;
    let rec = {
        let store = axiscomp::store::Store::open_read_only(&rig.store).expect("store");
        store.follower_map(id).expect("stored map")
    };
    assert!(rec.in_use);
    assert!(
        rec.name
            .ends_with(&format!(" + level at {planned} stations")),
        "{}",
        rec.name
    );
    assert!(rec.steps.is_some(), "the steps are kept with the new map");
    let map = &rec.map;
    let reference = map
        .vertical_reference
        .as_ref()
        .expect("the level's stations");
    assert_eq!(reference.stations.len(), planned);
    assert!(map.vertical_line.is_none());
    // The whole vertical, relative to its first point, against the truth.
    let truth = &rig.twin.plant.follower;
    let vp = &map.vertical_positions_mm;
    let x0 = vp[0];
    let (mut z2, mut worst_u, mut worst_um, mut max_u, mut n) =
        (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
    for (i, &x) in vp.iter().enumerate() {
        let err = (map.vertical_mm[i] - (truth.vertical(x) - truth.vertical(x0))) * 1e3;
        let u = map.vertical_u_mm[i] * 1e3;
        eprintln!("  vertical at {x:7.2} mm: map − truth {err:+.3} µm, u {u:.3} µm");
        worst_um = worst_um.max(err.abs());
        max_u = max_u.max(u);
        if u > 0.0 {
            worst_u = worst_u.max(err.abs() / u);
            z2 += (err / u).powi(2);
            n += 1;
        }
    }
    let rms_z = (z2 / n.max(1) as f64).sqrt();
    if let Some(e) = &l.error {
        eprintln!("the stations' note: {e}");
    }
    eprintln!(
        "level-referenced {:.1}–{:.1} mm: {planned} stations, {} points, RMS (map − truth)/u {rms_z:.2}, worst |map − truth| {worst_um:.3} µm = {worst_u:.2} u (largest u {max_u:.3} µm); u at mid-span {:?} µm from the steps alone, {:?} µm with the stations; mapped after {mapped_at:.1} s, {:.1} s of wall time so far",
        x0,
        vp[vp.len() - 1],
        vp.len(),
        l.u_mid_steps_um,
        l.u_mid_level_um,
        wall.elapsed().as_secs_f64()
    );
    assert!(n > 0);
    assert!(rms_z <= 2.0, "RMS (map − truth)/u {rms_z:.2}");
    assert!(worst_u <= 5.0, "a point {worst_u:.2} u from the truth");
    rig.stop().await;
}

/// The map in use checked on this set-up by the level's stations (`check_map`, issue 26): a
/// map made here passes, is stored with the set-up's bend ("… + checked on a set-up at N
/// stations", its check kept with it) and put in use, its vertical against the twin's true
/// one within its u. The same map with a step of 3 µm put into its vertical beyond 20 mm (the
/// rail changed since it was mapped) is refused, naming the span, nothing stored and the map
/// in use unchanged. Too few stations, and a map without a vertical, refused at the start.
#[tokio::test(start_paused = true)]
async fn the_service_checks_the_map_in_use_on_this_set_up_and_refuses_a_changed_rail() {
    use axiscomp::service::api::LevelRequest;
    let rig = level_rig().await;
    let check = |station_mm: f64| LevelRequest {
        station_mm: Some(station_mm),
        readings: Some(10),
        check_map: true,
        ..LevelRequest::default()
    };
    // The twin's certificate alone: no vertical to check.
    import_twin_certificate(&rig).await;
    let e = rig
        .request(Request::FollowerLevelStart(check(5.0)))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("has no vertical map to check on this set-up: map the follower"),
        "{e}"
    );
    let mapped = map_short(&rig).await;
    // Three stations cannot judge a cubic bend: refused before the carriage moves.
    let e = rig
        .request(Request::FollowerLevelStart(check(20.0)))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("3 stations from")
            && e.contains("needs 6 at least")
            && e.contains("smaller spacing"),
        "{e}"
    );
    let v = rig
        .request(Request::FollowerLevelStart(check(5.0)))
        .await
        .expect("check start");
    assert_eq!(
        (v["state"].as_str(), v["check_map"].as_bool()),
        (Some("stations"), Some(true)),
        "{v}"
    );
    let planned = v["stations"].as_array().map_or(0, Vec::len);
    assert!(planned >= 6, "{v}");
    let l = rig
        .wait_for(180, "the stations done", |s| {
            s.follower_level.as_ref().is_some_and(|l| !l.active())
        })
        .await
        .follower_level
        .expect("the stations' view");
    assert_eq!(l.state, "done", "{l:#?}");
    let id = l.map_id.expect("the checked map stored");
    let rec = {
        let store = axiscomp::store::Store::open_read_only(&rig.store).expect("store");
        store.follower_map(id).expect("stored map")
    };
    assert!(rec.in_use, "the checked map in use");
    assert!(
        rec.name
            .ends_with(&format!(" + checked on a set-up at {planned} stations")),
        "{}",
        rec.name
    );
    let reuse = rec.map.reuse.as_ref().expect("the check kept with the map");
    assert_eq!(reuse.stations, planned);
    assert!(reuse.worst_z <= reuse.limit_z, "{reuse:?}");
    assert!(
        rec.map.summary().iter().any(|l| l.contains("re-used")),
        "{:?}",
        rec.map.summary()
    );
    // Its vertical, relative to its first point, against the truth, as the level's test.
    let truth = &rig.twin.plant.follower;
    let (vp, v, u) = (
        &rec.map.vertical_positions_mm,
        &rec.map.vertical_mm,
        &rec.map.vertical_u_mm,
    );
    let (mut z2, mut worst) = (0.0f64, 0.0f64);
    for i in 0..vp.len() {
        let err = v[i] - (truth.vertical(vp[i]) - truth.vertical(vp[0]));
        let z = if u[i] > 0.0 { err / u[i] } else { 0.0 };
        z2 += z * z;
        worst = worst.max(z.abs());
    }
    let rms_z = (z2 / vp.len() as f64).sqrt();
    eprintln!(
        "checked on this set-up: {}; RMS (map − truth)/u {rms_z:.2}, worst {worst:.2} u",
        reuse.describe()
    );
    assert!(
        rms_z <= 2.0 && worst <= 5.0,
        "RMS {rms_z:.2} u, worst {worst:.2} u"
    );

    // The rail changed since it was mapped: a step of 3 µm in the stored vertical beyond
    // 20 mm. Put in use, then checked: refused, naming where.
    let mut changed = {
        let store = axiscomp::store::Store::open_read_only(&rig.store).expect("store");
        store.follower_map(mapped).expect("the mapped map")
    };
    for (x, v) in changed
        .map
        .vertical_positions_mm
        .iter()
        .zip(changed.map.vertical_mm.iter_mut())
    {
        if *x > 20.0 {
            *v += 3.0e-3;
        }
    }
    let changed_id = {
        let mut store = axiscomp::store::Store::open(&rig.store).expect("store");
        let stored = axiscomp::follower::StoredMap {
            map: changed.map.clone(),
            certificate: changed.certificate.clone(),
            steps: changed.steps.clone(),
        };
        store
            .insert_stored_follower_map(&stored, "mapped, then the rail changed", false)
            .expect("store the changed map")
    };
    rig.request(Request::FollowerMap {
        id: Some(changed_id),
    })
    .await
    .expect("the changed map put in use");
    rig.request(Request::FollowerLevelStart(check(5.0)))
        .await
        .expect("check start");
    let l = rig
        .wait_for(180, "the changed map's check done", |s| {
            s.follower_level
                .as_ref()
                .is_some_and(|l| l.map_from == changed_id && !l.active())
        })
        .await
        .follower_level
        .expect("the stations' view");
    let e = l.error.clone().unwrap_or_default();
    assert_eq!(l.state, "failed", "{l:#?}");
    assert!(
        e.contains("the map in use does not fit this set-up")
            && e.contains("the rail changed since it was mapped, most likely between")
            && e.contains("the map in use is unchanged"),
        "{e}"
    );
    eprintln!("refused: {e}");
    // The span named holds the step (encoder 20 mm; the carriage's stations a few tenths of
    // a millimetre off the encoder's).
    let span: Vec<f64> = e
        .split("most likely between ")
        .nth(1)
        .and_then(|t| t.split(" mm").next())
        .map(|t| t.split(" and ").filter_map(|x| x.parse().ok()).collect())
        .unwrap_or_default();
    assert!(
        span.len() == 2 && span[0] <= 20.0 && span[1] >= 20.0,
        "the span {span:?} does not hold the step at 20 mm"
    );
    let store = axiscomp::store::Store::open_read_only(&rig.store).expect("store");
    let in_use = store
        .follower_maps()
        .expect("maps")
        .into_iter()
        .find(|m| m.in_use)
        .map(|m| m.id);
    assert_eq!(
        in_use,
        Some(changed_id),
        "nothing stored, the map in use unchanged"
    );
    rig.stop().await;
}

/// A level's reading typed through the API: not a number, beyond the limit, or with no
/// stations under way, refused in words naming the field and what to do.
#[tokio::test(start_paused = true)]
async fn a_bad_level_reading_is_refused_in_words() {
    use axiscomp::service::api::LevelRequest;
    use axiscomp::service::api::follower::LEVEL_LIMIT_ARCSEC;
    let rig = ServiceRig::start(RigOptions {
        service_toml: SERVICE.into(),
        follower_toml: Some("level = \"manual\"\n".into()),
        ..RigOptions::default()
    })
    .await;
    let reading = |x: serde_json::Value| Request::FollowerLevelReading { arcsec: x };
    let e = rig
        .request(reading(serde_json::json!("NaN")))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("\"arcsec\" is \"NaN\": give the level's reading as a number of arcsec"),
        "{e}"
    );
    let e = rig
        .request(reading(serde_json::Value::Null))
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("follower_level_reading needs \"arcsec\""), "{e}");
    let e = rig
        .request(reading(serde_json::json!(LEVEL_LIMIT_ARCSEC + 0.5)))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("\"arcsec\" is 1000.5: give the level's reading within ±1000″"),
        "{e}"
    );
    let e = rig
        .request(reading(serde_json::json!(2.5)))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no level stations are under way: start them first"),
        "{e}"
    );
    // Nothing to fit with yet: the start refused, saying to map the follower first.
    let e = rig
        .request(Request::FollowerLevelStart(LevelRequest::default()))
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("map the follower first"), "{e}");
    for r in [Request::FollowerLevelStop, Request::FollowerLevelFinish] {
        let e = rig.request(r).await.unwrap_err().to_string();
        assert!(e.contains("no level stations are under way"), "{e}");
    }
    let v = rig
        .request(Request::FollowerLevelStatus)
        .await
        .expect("status");
    assert_eq!(v["state"], "idle", "{v}");
    // The same through the command line: refused, input to fix (exit 2); the status said.
    use crate::helpers::{run, stderr, stdout};
    let sock = rig.socket.display().to_string();
    let cli = |args: Vec<String>| {
        tokio::task::spawn_blocking(move || {
            let a: Vec<&str> = args.iter().map(String::as_str).collect();
            run(&a, "")
        })
    };
    let args = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let o = cli(args(&[
        "follower",
        "level",
        "--socket",
        &sock,
        "--reading",
        "1200",
    ]))
    .await
    .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("\"arcsec\" is 1200: give the level's reading within ±1000″"),
        "{}",
        stderr(&o)
    );
    let o = cli(args(&["follower", "level", "--socket", &sock, "--status"]))
        .await
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("no level stations since the service started"),
        "{}",
        stdout(&o)
    );
    let o = cli(args(&["follower", "level", "--socket", &sock]))
        .await
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("map the follower first"),
        "{}",
        stderr(&o)
    );
    rig.stop().await;
}
