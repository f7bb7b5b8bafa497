//! The event loop never waits on the disk (issue 25, must-show 3). Mid-run, another process (a
//! Python `sqlite3` shell, as a backup or an operator's `sqlite3` would) holds the store's
//! write lock for 5 s, the service's busy timeout. The service must go on: status answered
//! within 0.25 s, the snapshot moving, the PSD frames and the CAN traffic at their rates; the
//! captures taken meanwhile wait in the store's queue, and once the lock is gone every capture
//! of the run is stored exactly once.

use crate::helpers::{RigOptions, TempDir, twin_and_config};
use crate::serve::{FAST, align_and_start, ask, fail, serve, wait_snapshot};
use axiscomp::run::TargetKey;
use axiscomp::service::api::Request;
use axiscomp::service::control::Client;
use axiscomp::store::{RunId, RunState, Store};
use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// How long the other process holds the lock (s): the service's busy timeout.
const HOLD_S: f64 = 5.0;

/// Takes the write lock (BEGIN EXCLUSIVE), says so, holds it, lets go.
const LOCKER: &str = r#"
import sqlite3, sys, time
c = sqlite3.connect(sys.argv[1], isolation_level=None, timeout=30)
c.execute("BEGIN EXCLUSIVE")
print("locked", flush=True)
time.sleep(float(sys.argv[2]))
c.execute("COMMIT")
print("released", flush=True)
"#;

/// What the service showed over a stretch of time, asked every 100 ms.
#[derive(Debug, Default)]
struct Sample {
    asked: usize,
    /// The slowest status reply, connection included (s).
    slowest_s: f64,
    /// PSD frames per second, from the snapshot's frame counter and time.
    psd_hz: f64,
    /// The drive's TPDOs per second as the snapshot states them, averaged and at least (the
    /// SYNC is quiet while the carriage rests, so the rate follows the motion).
    can_hz: f64,
    can_min_hz: f64,
    /// The drive's heartbeat was seen in every snapshot.
    can_up: bool,
    /// The run's captures at the start and the end.
    captures: (usize, usize),
}

async fn sample(socket: &Path, over: Duration) -> Sample {
    let end = Instant::now() + over;
    let mut s = Sample::default();
    let mut first: Option<(u64, i64)> = None;
    let mut last: Option<(u64, i64)> = None;
    let mut can = Vec::new();
    s.can_up = true;
    while Instant::now() < end {
        let t0 = Instant::now();
        let snap = match Client::connect(socket).await {
            Ok(mut c) => tokio::time::timeout(Duration::from_secs(10), c.status()).await,
            Err(e) => panic!("the control socket refused a connection: {e}"),
        };
        let took = t0.elapsed().as_secs_f64();
        let Ok(Ok(snap)) = snap else {
            panic!("status not answered within 10 s");
        };
        s.asked += 1;
        s.slowest_s = s.slowest_s.max(took);
        if let Some(p) = &snap.psd {
            first.get_or_insert((p.seq, snap.unix_us));
            last = Some((p.seq, snap.unix_us));
        }
        can.push(snap.links.can.rate_hz);
        s.can_up &= snap.links.can.state == "up";
        let n = snap.run.as_ref().map_or(0, |r| r.captures);
        if s.asked == 1 {
            s.captures.0 = n;
        }
        s.captures.1 = n;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    if let (Some((s0, t0)), Some((s1, t1))) = (first, last)
        && t1 > t0
    {
        s.psd_hz = (s1 - s0) as f64 / ((t1 - t0) as f64 * 1e-6);
    }
    s.can_hz = can.iter().sum::<f64>() / can.len().max(1) as f64;
    s.can_min_hz = can.iter().copied().fold(f64::INFINITY, f64::min);
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_locked_by_another_process_for_5_s_holds_up_nothing_but_the_store() {
    let _machine = crate::helpers::exclusive().await;
    let dir = TempDir::new("store-lock");
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
    let expected = started["captures_expected"].as_u64().unwrap_or(0) as usize;
    let end = Instant::now() + Duration::from_secs(60);
    loop {
        let n = ask(&socket, &Request::RunStatus)
            .await
            .and_then(|s| s["captures"].as_u64())
            .unwrap_or(0);
        if n >= 3 {
            break;
        }
        if Instant::now() > end {
            let _ = child.kill();
            fail(&log, "no 3 captures within 60 s".into());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    let before = sample(&socket, Duration::from_secs(2)).await;
    let store_path = dir.path("state").join("axiscomp.db");
    let mut locker = Command::new("python3")
        .arg("-c")
        .arg(LOCKER)
        .arg(&store_path)
        .arg(HOLD_S.to_string())
        .stdout(Stdio::piped())
        .spawn()
        .expect("python3 holds the store's lock");
    let out = locker.stdout.take().expect("the locker's stdout");
    let mut lines = std::io::BufReader::new(out).lines();
    let said = tokio::task::spawn_blocking(move || {
        let first = lines.next().and_then(Result::ok);
        (first, lines)
    })
    .await
    .expect("the locker's first line");
    assert_eq!(
        said.0.as_deref(),
        Some("locked"),
        "the locker took the lock"
    );
    let locked_at = Instant::now();
    let during = sample(&socket, Duration::from_secs_f64(HOLD_S - 0.3)).await;
    let status = tokio::task::spawn_blocking(move || locker.wait())
        .await
        .expect("join")
        .expect("the locker ends");
    assert!(status.success(), "the locker let go of the lock: {status}");
    let held_s = locked_at.elapsed().as_secs_f64();

    // The run ends (every capture stored) once the lock is gone.
    let end = Instant::now() + Duration::from_secs(150);
    let state = loop {
        let st = ask(&socket, &Request::RunStatus).await;
        if let Some(s) = st.as_ref().and_then(|s| s["state"].as_str())
            && s != "running"
        {
            break s.to_string();
        }
        if Instant::now() > end {
            let _ = child.kill();
            fail(&log, format!("the run did not end within 150 s: {st:?}"));
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let _ = child.kill();
    let _ = child.wait();
    drop(twin);

    let store = Store::open_read_only(&store_path).expect("store");
    let rec = store.run(run).expect("the run");
    let mut count: BTreeMap<TargetKey, usize> = BTreeMap::new();
    for c in store.captures(run).expect("captures") {
        *count.entry(TargetKey::of(&c)).or_default() += 1;
    }
    let twice: Vec<_> = count.iter().filter(|(_, n)| **n != 1).collect();
    eprintln!(
        "store lock: held {held_s:.1} s by another process; status asked {} times, slowest {:.3} s \
         (before: {:.3} s); PSD frames {:.0}/s (before {:.0}/s); drive TPDOs {:.0}/s, at least {:.0}/s \
         (before {:.0}/s), heartbeat up throughout: {}; \
         run captures {} -> {} during the lock; run {state}: {} of {expected} captures stored, \
         more than once {twice:?}",
        during.asked,
        during.slowest_s,
        before.slowest_s,
        during.psd_hz,
        before.psd_hz,
        during.can_hz,
        during.can_min_hz,
        before.can_hz,
        during.can_up,
        during.captures.0,
        during.captures.1,
        count.len()
    );
    if during.slowest_s > 0.25 {
        fail(
            &log,
            format!(
                "a status reply took {:.3} s while the store was locked (at most 0.25 s)",
                during.slowest_s
            ),
        );
    }
    // The PSD frames keep their rate; the drive keeps its heartbeat and its PDOs flowing
    // (their rate follows the SYNC, which is quiet while the carriage rests).
    if during.psd_hz < 0.9 * before.psd_hz || !during.can_up || during.can_min_hz <= 0.0 {
        fail(
            &log,
            format!(
                "the service slowed while the store was locked: PSD {:.0} -> {:.0} frames/s, drive TPDOs at least {:.0}/s, heartbeat up throughout: {}",
                before.psd_hz, during.psd_hz, during.can_min_hz, during.can_up
            ),
        );
    }
    if state != "finished" || rec.state != RunState::Finished {
        fail(&log, format!("the run ended {state}: {}", rec.notes));
    }
    if count.len() != expected || !twice.is_empty() {
        fail(
            &log,
            format!(
                "{} distinct captures stored of {expected}, more than once {twice:?}",
                count.len()
            ),
        );
    }
}
