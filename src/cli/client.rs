//! The subcommands' side of the running service's control socket: where it is, the runtime a
//! request runs on, a refusal as input to fix, and following a procedure's status to its end.

use super::InputError;
use anyhow::{Context, Result};
use axiscomp::service::api::Request;
use axiscomp::service::control::{Client, ClientError};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// How often [`follow`] asks for the status.
const FOLLOW_EVERY: Duration = Duration::from_secs(2);

/// The control socket: `--socket`, else the configured one.
pub(super) fn socket_path(socket: Option<&Path>, config: Option<&Path>) -> Result<PathBuf> {
    Ok(match socket {
        Some(s) => s.to_path_buf(),
        None => super::service::settings(config)?.service.socket,
    })
}

pub(super) fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// A request the service refused is input to fix (exit code 2).
pub(super) fn refused(e: ClientError) -> anyhow::Error {
    match e {
        ClientError::Refused(m) => InputError(m).into(),
        e => e.into(),
    }
}

/// Seconds as people read them: "45 s", "3.4 min", "1.7 h".
pub(super) fn duration_words(s: f64) -> String {
    if !s.is_finite() || s < 0.0 {
        "?".into()
    } else if s < 90.0 {
        format!("{s:.0} s")
    } else if s < 5400.0 {
        format!("{:.1} min", s / 60.0)
    } else {
        format!("{:.1} h", s / 3600.0)
    }
}

/// Ctrl-C while the command line follows a procedure the service runs: listened for from
/// before the procedure starts (a SIGINT in between would otherwise end the command without a
/// word), and what to say then: the procedure goes on in the service.
pub(super) struct Leave {
    sigint: tokio::signal::unix::Signal,
    /// What goes on, and the commands to follow and to stop it.
    words: String,
}

impl Leave {
    /// Listen for Ctrl-C from now on (inside the runtime).
    pub(super) fn listen(words: String) -> Result<Leave> {
        use tokio::signal::unix::{SignalKind, signal};
        let sigint = signal(SignalKind::interrupt()).context("installing the Ctrl-C handler")?;
        Ok(Leave { sigint, words })
    }
}

/// Follow a procedure on the service until it is over: ask for its `status` every 2 s, print
/// its `progress_line` on standard error whenever the line changes, and return the first
/// status in which it is no longer `running`. Ctrl-C leaves it running in the service and says
/// so (`Leave`; exit code 130).
pub(super) async fn follow(
    c: &mut Client,
    status: &Request,
    progress_line: fn(&serde_json::Value) -> String,
    running: fn(&serde_json::Value) -> bool,
    leave: &mut Leave,
) -> Result<serde_json::Value> {
    let mut last = String::new();
    loop {
        tokio::select! {
            () = tokio::time::sleep(FOLLOW_EVERY) => {}
            _ = leave.sigint.recv() => {
                return Err(super::Interrupted(format!("Ctrl-C: {}", leave.words)).into());
            }
        }
        let v = c.request(status).await?;
        let line = progress_line(&v);
        if line != last {
            eprintln!("{line}");
            last = line;
        }
        if !running(&v) {
            return Ok(v);
        }
    }
}
