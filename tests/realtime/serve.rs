//! The service as a real process beside the twin: start it, ask it, wait for its snapshot,
//! align and start a run, and the failure message with the tails of its logs.

use crate::helpers::{bin, short_plan};
use axiscomp::service::api::Request;
use axiscomp::service::control::Client;
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::Duration;

/// Handovers and captures quicker than the production defaults (as the console test), so
/// the 20 captures take about half a minute.
pub const FAST: &str = "[tracking]\nrest_ms = 200\naverage_frames = 100\nsettle_ms = 100\n\n\
                    [capture]\nframes = 100\nsettle_ms = 200\n";

/// `axiscomp serve` as a child process, its output in `log`.
pub fn serve(config: &Path, log: &Path) -> Child {
    let out = std::fs::File::create(log).expect("service log");
    let err = out.try_clone().expect("service log");
    bin()
        .args(["serve", "--config"])
        .arg(config)
        .env("RUST_LOG", "info")
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(err)
        .spawn()
        .expect("spawn axiscomp serve")
}

/// The tail of each service log, for a failure message.
pub fn logs(logs: &[PathBuf]) -> String {
    logs.iter()
        .map(|p| {
            let text = std::fs::read_to_string(p).unwrap_or_default();
            let lines: Vec<&str> = text
                .lines()
                .filter(|l| !l.contains("request=RunStatus"))
                .collect();
            let tail = lines[lines.len().saturating_sub(30)..].join("\n");
            format!("---- {} ----\n{tail}", p.display())
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Fail the test with `what` and the tails of the service logs.
pub fn fail(log: &[PathBuf], what: String) -> ! {
    panic!("{what}\n{}", logs(log))
}

/// The service's answer to `req`, or None while it does not answer (not up yet, or killed).
pub async fn ask(socket: &Path, req: &Request) -> Option<serde_json::Value> {
    ask_within(socket, req, 5).await
}

/// The service's answer to `req` within `secs`, or None.
pub async fn ask_within(socket: &Path, req: &Request, secs: u64) -> Option<serde_json::Value> {
    let mut c = Client::connect(socket).await.ok()?;
    tokio::time::timeout(Duration::from_secs(secs), c.request(req))
        .await
        .ok()?
        .ok()
}

/// Wait up to `secs` for the service's snapshot to satisfy `pred`.
pub async fn wait_snapshot(
    socket: &Path,
    secs: u64,
    pred: impl Fn(&axiscomp::service::api::snapshot::Snapshot) -> bool,
) -> bool {
    let end = axiscomp::util::clock::now() + Duration::from_secs(secs);
    while axiscomp::util::clock::now() < end {
        if let Ok(mut c) = Client::connect(socket).await
            && let Ok(s) = c.status().await
            && pred(&s)
        {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    false
}

/// Align the short plan's travel (the pre-run check wants it) and start the run: its reply.
pub async fn align_and_start(
    socket: &Path,
    twin: &axiscomp::sim::twin::Twin,
    log: &[PathBuf],
) -> serde_json::Value {
    let travel = axiscomp::run::Plan::new(short_plan())
        .expect("plan")
        .travel_mm();
    crate::helpers::align_service(socket, twin, travel).await;
    // The answer comes once the run is stored and its program is with the twin's CNC: on CI's
    // two cores beside the storm and the soak that took more than 5 s once (at 2a27ceb), and
    // how fast it answers is not what these tests check.
    ask_within(
        socket,
        &Request::RunStart {
            plan: short_plan(),
            dialect: Some("linuxcnc".into()),
            notes: None,
        },
        30,
    )
    .await
    .unwrap_or_else(|| fail(log, "run_start was not answered".into()))
}
