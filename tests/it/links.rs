//! Field links that tell the truth (issue 18): the live service against an independent
//! pymodbus I/O module that misbehaves on command (`tests/interop/pymodbus_faults.py`, run by
//! `tests/interop/links.sh`): one exception, exceptions that persist, a module that accepts
//! connections and never answers, an outage. Each time the snapshot's link state and detail,
//! its alarms and the frame's validity are asserted. And a drive that is not on the bus.

use crate::helpers::{RigOptions, ServiceRig, free_port};
use axiscomp::service::api::snapshot::Snapshot;
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::Duration;
use tokio::sync::mpsc;

/// The pymodbus module and its command pipe (its stdout lines come through a thread).
struct Peer {
    child: Child,
    stdin: ChildStdin,
    stdout: mpsc::UnboundedReceiver<String>,
}

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Peer {
    async fn start(port: u16) -> Peer {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let mut child = Command::new("python3")
            .arg(root.join("tests/interop/pymodbus_faults.py"))
            .arg("--port")
            .arg(port.to_string())
            .current_dir(root)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("run python3 tests/interop/pymodbus_faults.py");
        let stdin = child.stdin.take().expect("stdin");
        let out = child.stdout.take().expect("stdout");
        let (tx, stdout) = mpsc::unbounded_channel();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        let mut peer = Peer {
            child,
            stdin,
            stdout,
        };
        let first = peer.line(20).await;
        let v: serde_json::Value = serde_json::from_str(&first).expect("JSON line");
        assert_eq!(v["port"], port, "{first}");
        peer
    }

    /// The module's next line on stdout, within `secs`.
    async fn line(&mut self, secs: u64) -> String {
        tokio::time::timeout(Duration::from_secs(secs), self.stdout.recv())
            .await
            .unwrap_or_else(|_| panic!("pymodbus_faults.py said nothing for {secs} s"))
            .expect("pymodbus_faults.py ended (is pymodbus >= 3.12 installed?)")
    }

    /// Send a command and wait until the module says it is in effect.
    async fn command(&mut self, cmd: &str) {
        writeln!(self.stdin, "{cmd}").expect("command to pymodbus_faults.py");
        self.stdin.flush().expect("flush");
        assert_eq!(self.line(10).await, format!("ok {cmd}"));
    }
}

fn alarm<'a>(s: &'a Snapshot, code: &str) -> Option<&'a str> {
    s.alarms
        .iter()
        .find(|a| a.code == code && a.active)
        .map(|a| a.text.as_str())
}

fn psd_valid(s: &Snapshot) -> bool {
    s.psd.as_ref().is_some_and(|p| p.valid)
}

fn seq(s: &Snapshot) -> u64 {
    s.psd.as_ref().map(|p| p.seq).unwrap_or(0)
}

fn rate(s: &Snapshot) -> f64 {
    s.psd.as_ref().map(|p| p.rate_hz).unwrap_or(0.0)
}

/// Good replies again: up, valid frames coming, no I/O alarm.
async fn recovered(rig: &ServiceRig, what: &str) -> Snapshot {
    let before = seq(&rig.snapshot().await);
    rig.wait_for(10, what, |s| {
        s.links.io.state == "up"
            && psd_valid(s)
            && seq(s) > before + 20
            && alarm(s, "io-link-down").is_none()
            && alarm(s, "io-exception").is_none()
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymodbus >= 3.12: run by tests/interop/links.sh"]
async fn interop_field_links_tell_the_truth() {
    let port = free_port();
    let mut peer = Peer::start(port).await;
    let rig = ServiceRig::start(RigOptions {
        io_toml: Some(format!(
            "address = \"127.0.0.1:{port}\"\nrate_hz = 100.0\ntimeout_ms = 200\n\
             reconnect_min_ms = 100\nreconnect_max_ms = 400\n"
        )),
        wait_ready: false,
        ..RigOptions::default()
    })
    .await;

    // Good replies: up, valid frames, the rate that of the last second (frames counted by
    // their sequence numbers over 1.5 s, within 10 %).
    rig.wait_for(20, "the link up, valid frames", |s| {
        s.links.io.state == "up" && psd_valid(s) && rate(s) > 50.0
    })
    .await;
    let s0 = rig.snapshot().await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let s = rig.snapshot().await;
    let counted = (seq(&s) - seq(&s0)) as f64 / ((s.unix_us - s0.unix_us) as f64 * 1e-6);
    assert!(
        (rate(&s) - counted).abs() <= 0.1 * counted,
        "rate {:.1}/s, counted {counted:.1}/s",
        rate(&s)
    );
    assert_eq!(s.links.io.state, "up");
    assert_eq!(s.links.io.exceptions, 0);
    assert!(alarm(&s, "io-link-down").is_none() && alarm(&s, "io-exception").is_none());
    eprintln!("up: {:.1} frames/s shown, {counted:.1} counted", rate(&s));

    // (a) One exception: named in the status and counted; the link stays up, no alarm.
    peer.command("once 2").await;
    let s = rig
        .wait_for(5, "the exception named in the status", |s| {
            s.links.io.exceptions >= 1
        })
        .await;
    let detail = s.links.io.detail.clone().unwrap_or_default();
    assert!(
        detail.contains("exception 0x02 (illegal data address)"),
        "detail: {detail}"
    );
    let s = rig
        .wait_for(5, "up again after the exception", |s| {
            s.links.io.state == "up" && psd_valid(s)
        })
        .await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let s2 = rig.snapshot().await;
    assert_eq!(s2.links.io.exceptions, 1, "one exception, counted once");
    assert!(
        alarm(&s2, "io-exception").is_none(),
        "one exception is no alarm"
    );
    assert!(seq(&s2) > seq(&s) + 100, "frames go on after one exception");

    // (b) Exceptions that persist: refusing, the frame stale and invalid, the rate falls to
    // zero within the last second, and after 1 s the alarm names the exception.
    peer.command("exception 4").await;
    let t = axiscomp::util::clock::now();
    let s = rig
        .wait_for(3, "refusing, the last frame invalid", |s| {
            s.links.io.state == "refusing" && !psd_valid(s)
        })
        .await;
    let detail = s.links.io.detail.clone().unwrap_or_default();
    assert!(
        detail.contains("exception 0x04 (server device failure)"),
        "detail: {detail}"
    );
    let s = rig
        .wait_for(5, "the io-exception alarm", |s| {
            alarm(s, "io-exception").is_some()
        })
        .await;
    let took = axiscomp::util::clock::since(t);
    let text = alarm(&s, "io-exception").unwrap_or_default();
    assert!(
        text.contains("exception 0x04 (server device failure)"),
        "{text}"
    );
    assert!(
        took >= Duration::from_millis(900),
        "the alarm waits for exceptions to persist (1 s), came after {took:?}"
    );
    eprintln!(
        "persistent exceptions: alarm after {:.2} s",
        took.as_secs_f64()
    );
    tokio::time::sleep(Duration::from_millis(1300).saturating_sub(axiscomp::util::clock::since(t)))
        .await;
    let s = rig.snapshot().await;
    let frozen = seq(&s);
    assert!(!psd_valid(&s), "a frozen frame is not valid");
    let p = s.psd.as_ref().expect("the last frame is still shown");
    assert!(p.age_ms > 1000.0, "its age is shown: {} ms", p.age_ms);
    assert!(
        rate(&s) < 1.0,
        "no frames in the last second, rate {:.1}/s",
        rate(&s)
    );
    assert_eq!(s.links.io.state, "refusing");
    assert!(alarm(&s, "io-link-down").is_none(), "the module answers");
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        seq(&rig.snapshot().await),
        frozen,
        "no frame from exceptions"
    );
    peer.command("ok").await;
    let s = recovered(&rig, "good replies after the exceptions").await;
    assert!(alarm(&s, "io-exception").is_none());

    // (c) A module that accepts connections and never answers is never up, and the alarm
    // stays raised from its first timeout.
    peer.command("hang").await;
    rig.wait_for(5, "the io-link-down alarm, the last frame stale", |s| {
        alarm(s, "io-link-down").is_some() && !psd_valid(s)
    })
    .await;
    let mut seen = std::collections::BTreeSet::new();
    let end = axiscomp::util::clock::now() + Duration::from_secs(2);
    let mut c = rig.client().await;
    while axiscomp::util::clock::now() < end {
        let s = c.status().await.expect("status");
        assert_ne!(s.links.io.state, "up", "a hung module is never up");
        assert!(
            alarm(&s, "io-link-down").is_some(),
            "the alarm stays: {:?}",
            s.links.io
        );
        assert!(!psd_valid(&s), "no valid frame from a hung module");
        seen.insert(s.links.io.state.clone());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    eprintln!("hung module: states seen {seen:?}");
    assert!(
        seen.contains("connected") || seen.contains("down"),
        "{seen:?}"
    );
    peer.command("ok").await;
    recovered(&rig, "good replies after the hang").await;

    // (d) An outage: down, the alarm, the last frame invalid once stale, the rate to zero.
    peer.command("outage").await;
    let t = axiscomp::util::clock::now();
    let s = rig
        .wait_for(3, "down with the alarm, the frame invalid", |s| {
            s.links.io.state != "up" && alarm(s, "io-link-down").is_some() && !psd_valid(s)
        })
        .await;
    eprintln!(
        "outage: shown after {:.2} s, state {}",
        axiscomp::util::clock::since(t).as_secs_f64(),
        s.links.io.state
    );
    tokio::time::sleep(Duration::from_millis(1300).saturating_sub(axiscomp::util::clock::since(t)))
        .await;
    let s = rig.snapshot().await;
    assert!(rate(&s) < 1.0, "rate {:.1}/s", rate(&s));
    assert!(!psd_valid(&s));
    peer.command("ok").await;
    recovered(&rig, "good replies after the outage").await;
    rig.stop().await;
}

/// A follower drive that is not on the bus (the service looks for node 9; the twin's drive is
/// node 1): the `drive-absent` alarm names the node, the CAN link shows no heartbeat.
#[tokio::test(start_paused = true)]
async fn an_absent_drive_raises_an_alarm() {
    let rig = ServiceRig::start(RigOptions {
        follower_toml: Some("node_id = 9\n".into()),
        wait_ready: false,
        ..RigOptions::default()
    })
    .await;
    let t = axiscomp::util::clock::now();
    let s = rig
        .wait_for(20, "the drive-absent alarm", |s| {
            alarm(s, "drive-absent").is_some()
        })
        .await;
    let text = alarm(&s, "drive-absent").unwrap_or_default();
    assert!(text.contains("node 9"), "{text}");
    assert_eq!(s.links.can.state, "no heartbeat");
    assert_eq!(s.follower.state, "unknown");
    eprintln!(
        "absent drive: alarm after {:.1} s",
        axiscomp::util::clock::since(t).as_secs_f64()
    );
    rig.stop().await;
}
