//! Crash and resume (issue 4, must-show 4) with the service as a real process: the twin runs
//! in the test (its CNC executes the part programs the service sends), `axiscomp serve` is the
//! built binary; a run is started, the service is killed with SIGKILL mid-run and started again
//! on the same store, and the run must finish with every (run, target, direction) capture stored
//! exactly once, each under the direction the carriage came from.

use crate::helpers::{RigOptions, TempDir, short_plan, twin_and_config};
use crate::serve::{FAST, align_and_start, ask, fail, serve, wait_snapshot};
use axiscomp::run::{Direction, TargetKey};
use axiscomp::service::api::Request;
use axiscomp::store::{RunId, RunState, Store};
use std::collections::BTreeMap;
use std::time::Duration;

/// Kill the service once this many captures are stored.
const KILL_AFTER: u64 = 7;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_mid_run_and_restart_finishes_with_every_capture_once() {
    let _machine = crate::helpers::exclusive().await;
    let dir = TempDir::new("resume");
    let (twin, _, config, socket) = twin_and_config(
        RigOptions {
            service_toml: FAST.into(),
            twin_cnc: true,
            ..RigOptions::default()
        },
        &dir,
    )
    .await;
    let log = [dir.path("serve-1.log"), dir.path("serve-2.log")];
    let mut child = serve(&config, &log[0]);

    let ready = |s: &axiscomp::service::api::snapshot::Snapshot| {
        s.follower.homed && s.tracking.valid && s.tracking.at_rest
    };
    if !wait_snapshot(&socket, 60, ready).await {
        let _ = child.kill();
        fail(
            &log,
            "the service did not come up with the stitch referenced within 60 s".into(),
        );
    }
    let started = align_and_start(&socket, &twin, &log).await;
    let run = RunId(started["run_id"].as_i64().unwrap_or(0));
    let expected = started["captures_expected"].as_u64().unwrap_or(0);
    assert_eq!(expected, 20, "{started}");

    // Wait for the captures, then SIGKILL (std's Child::kill on Unix) the service mid-run.
    let end = axiscomp::util::clock::now() + Duration::from_secs(60);
    let at_kill = loop {
        let st = ask(&socket, &Request::RunStatus).await;
        let n = st
            .as_ref()
            .and_then(|s| s["captures"].as_u64())
            .unwrap_or(0);
        if n >= KILL_AFTER {
            break n;
        }
        if axiscomp::util::clock::now() > end {
            let _ = child.kill();
            fail(
                &log,
                format!("no {KILL_AFTER} captures within 60 s: {st:?}"),
            );
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    child.kill().expect("SIGKILL the service");
    let status = child.wait().expect("reap the service");
    assert!(!status.success(), "killed, not exited: {status:?}");
    let store_path = dir.path("state").join("axiscomp.db");
    let stored_at_kill = Store::open_read_only(&store_path)
        .and_then(|s| s.captures(run))
        .map(|c| c.len())
        .unwrap_or(0);
    // The twin's CNC goes on with the program while the service is down.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let mut child = serve(&config, &log[1]);

    let end = axiscomp::util::clock::now() + Duration::from_secs(150);
    let state = loop {
        let st = ask(&socket, &Request::RunStatus).await;
        if let Some(s) = st.as_ref().and_then(|s| s["state"].as_str())
            && s != "running"
        {
            break s.to_string();
        }
        if axiscomp::util::clock::now() > end {
            let _ = child.kill();
            fail(
                &log,
                format!("the resumed run did not end within 150 s: {st:?}"),
            );
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let _ = child.kill();
    let _ = child.wait();
    drop(twin);

    let store = Store::open_read_only(&store_path).expect("store");
    let rec = store.run(run).expect("the run");
    let captures = store.captures(run).expect("captures");
    let mut count: BTreeMap<TargetKey, usize> = BTreeMap::new();
    for c in &captures {
        *count.entry(TargetKey::of(c)).or_default() += 1;
    }
    let p = axiscomp::run::Plan::new(short_plan()).expect("plan");
    let want: Vec<TargetKey> = p.steps().iter().filter_map(|s| s.target).collect();
    let missing: Vec<_> = want.iter().filter(|k| !count.contains_key(k)).collect();
    let twice: Vec<_> = count.iter().filter(|(_, n)| **n != 1).collect();
    eprintln!(
        "resume: killed at {at_kill} captures ({stored_at_kill} stored), run {state}: {} captures stored of {expected}, missing {missing:?}, more than once {twice:?}",
        captures.len()
    );
    if state != "finished" || rec.state != RunState::Finished {
        fail(
            &log,
            format!("the run ended {state} ({:?}): {}", rec.state, rec.notes),
        );
    }
    if !missing.is_empty() || !twice.is_empty() || captures.len() != want.len() {
        fail(
            &log,
            format!(
                "not every capture exactly once: missing {missing:?}, more than once {twice:?}"
            ),
        );
    }
    // Each capture under the direction the carriage came from: the twin's 5 µm backlash puts
    // every downward capture of a target above every upward one.
    for (i, _) in p.targets.iter().enumerate() {
        let dy = |d: Direction| -> Vec<f64> {
            captures
                .iter()
                .filter(|c| c.target_index as usize == i && c.direction == d)
                .map(|c| c.errors.dy * 1e3)
                .collect()
        };
        let (up, down) = (dy(Direction::Up), dy(Direction::Down));
        let top_up = up.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let low_down = down.iter().copied().fold(f64::INFINITY, f64::min);
        if top_up >= low_down {
            fail(
                &log,
                format!(
                    "target {i}: an upward capture reads above a downward one (dy µm up {up:?}, down {down:?}): a direction was mislabelled"
                ),
            );
        }
    }
}

/// A store that refuses writes for a while (another process holds it locked past the busy
/// timeout, as a full disk refuses them): the capture is not stored, the `store` alarm says so,
/// and once a later capture is stored the alarm clears (the fault storm found it staying up
/// after the disk had room again); no capture is stored twice.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_refusing_writes_mid_run_raises_the_store_alarm_and_clears_it() {
    let _machine = crate::helpers::exclusive().await;
    let dir = TempDir::new("store-outage");
    let (twin, _, config, socket) = twin_and_config(
        RigOptions {
            service_toml: FAST.into(),
            twin_cnc: true,
            ..RigOptions::default()
        },
        &dir,
    )
    .await;
    let log = [dir.path("serve.log")];
    let mut child = serve(&config, &log[0]);
    let ready = |s: &axiscomp::service::api::snapshot::Snapshot| {
        s.follower.homed && s.tracking.valid && s.tracking.at_rest
    };
    if !wait_snapshot(&socket, 60, ready).await {
        let _ = child.kill();
        fail(&log, "the service did not come up within 60 s".into());
    }
    let started = align_and_start(&socket, &twin, &log).await;
    let run = RunId(started["run_id"].as_i64().unwrap_or(0));
    let captures = |n: u64| {
        let socket = socket.clone();
        async move {
            ask(&socket, &Request::RunStatus)
                .await
                .and_then(|s| s["captures"].as_u64())
                .is_some_and(|c| c >= n)
        }
    };
    let end = axiscomp::util::clock::now() + Duration::from_secs(60);
    while !captures(2).await {
        if axiscomp::util::clock::now() > end {
            let _ = child.kill();
            fail(&log, "no 2 captures within 60 s".into());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // Another writer holds the store: the service's writes wait the 5 s busy timeout and fail.
    let store_path = dir.path("state").join("axiscomp.db");
    let blocker = rusqlite::Connection::open(&store_path).expect("open the store");
    blocker
        .execute_batch("BEGIN EXCLUSIVE")
        .expect("lock the store");
    let alarm = |active: bool| {
        move |s: &axiscomp::service::api::snapshot::Snapshot| {
            s.alarms
                .iter()
                .any(|a| a.code == "store" && a.active && a.text.contains("capture not stored"))
                == active
        }
    };
    // Held until a capture has failed (the run may be waiting for the carriage's pass).
    let raised = wait_snapshot(&socket, 150, alarm(true)).await;
    blocker.execute_batch("COMMIT").expect("unlock the store");
    drop(blocker);
    if !raised {
        let _ = child.kill();
        fail(&log, "no store alarm while the store was locked".into());
    }
    if !wait_snapshot(&socket, 60, alarm(false)).await {
        let _ = child.kill();
        fail(
            &log,
            "the store alarm stayed up after the store took writes again".into(),
        );
    }
    // Whether the run then finishes is resume's other test; here: nothing stored twice.
    let _ = child.kill();
    let _ = child.wait();
    drop(twin);
    let store = Store::open_read_only(&store_path).expect("store");
    let mut count: BTreeMap<TargetKey, usize> = BTreeMap::new();
    for c in store.captures(run).expect("captures") {
        *count.entry(TargetKey::of(&c)).or_default() += 1;
    }
    let twice: Vec<_> = count.iter().filter(|(_, n)| **n != 1).collect();
    assert!(
        !count.is_empty() && twice.is_empty(),
        "{} captures stored, more than once {twice:?}",
        count.len()
    );
}
