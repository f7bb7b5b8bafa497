//! The control API (DESIGN §8): a Unix socket, newline-delimited JSON. One request per line,
//! one response per line (`{"ok":true,...}` or `{"ok":false,"error":"..."}`); `subscribe` turns
//! the connection into a stream of snapshots (`{"snapshot":{...}}` per line).
//!
//! Viewing (`status`, `subscribe`, `run_status`, `runs`, `run_result`, `audit`,
//! `table_list`, `table_status`) needs the viewer role; anything that changes state needs the operator role, and the service writes it
//! to the audit log; the `status` reply names the peer's `user` and `role`. Roles come from the peer's credentials (`peer`). The socket file
//! admits only its owner and the two role groups ([`open_to_roles`]): others are refused on connect
//! by the kernel; within, access is decided per request, so a viewer's refusal can say why.

use super::api::snapshot::Snapshot;
use super::api::{Request, Role};
use super::peer::{Peer, RolePolicy};
use super::shutdown::Shutdown;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::{mpsc, oneshot, watch};

/// Longest accepted request line (bytes): a longer one is answered with an error and the
/// connection closed, so a connection never buffers more than this.
pub const MAX_LINE: usize = 64 * 1024;

/// A refused connection is logged at most this often (with the count refused meanwhile).
const REFUSAL_LOG_EVERY: Duration = Duration::from_secs(10);

/// A request handed to the service core, with who asked and where to answer.
#[derive(Debug)]
pub struct Command {
    pub request: Request,
    pub peer: Peer,
    pub reply: oneshot::Sender<Result<serde_json::Value, String>>,
}

impl Command {
    /// The audit-log entry for an operator request (who, when, what); `None` for a viewer's.
    pub fn audit_entry(&self) -> Option<crate::store::AuditEntry> {
        if self.request.needs() != Role::Operator {
            return None;
        }
        let request = serde_json::to_value(&self.request).unwrap_or_default();
        let who = crate::store::Actor {
            uid: Some(self.peer.uid),
            user: Some(self.peer.user.clone()),
            pid: self.peer.pid,
        };
        Some(super::results::audit_entry(
            crate::store::now_us(),
            who,
            "operator",
            &request,
        ))
    }
}

/// Why the control socket could not be served.
#[derive(Debug, Error)]
pub enum ControlError {
    #[error("control socket {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// Bind the control socket at `path`: creates the parent directory, replaces a stale socket,
/// and lets only its owner connect until [`open_to_roles`] admits the role groups.
pub fn bind(path: &Path) -> Result<UnixListener, ControlError> {
    let err = |source| ControlError::Io {
        path: path.display().to_string(),
        source,
    };
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir).map_err(err)?;
    }
    if path.exists() {
        std::fs::remove_file(path).map_err(err)?;
    }
    let listener = UnixListener::bind(path).map_err(err)?;
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).map_err(err)?;
    Ok(listener)
}

/// Let the policy's operator and viewer groups connect to the socket at `path` (an access
/// ACL; mode 0660 as `ls` shows it, nothing for others). On a file system without POSIX ACLs
/// the socket is opened to every local user instead, with a warning: requests are still
/// checked per role.
pub fn open_to_roles(path: &Path, policy: &RolePolicy) -> Result<(), ControlError> {
    let gids: Vec<u32> = [policy.operator_gid, policy.viewer_gid]
        .into_iter()
        .flatten()
        .collect();
    match super::peer::open_to_groups(path, &gids) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::Unsupported => {
            tracing::warn!(
                "control socket {}: the file system has no POSIX ACLs, so every local user may connect (requests are still checked per role)",
                path.display()
            );
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o666)).map_err(
                |source| ControlError::Io {
                    path: path.display().to_string(),
                    source,
                },
            )
        }
        Err(source) => Err(ControlError::Io {
            path: path.display().to_string(),
            source,
        }),
    }
}

/// Serve the control socket until shutdown. Each connection gets its own task.
#[allow(clippy::too_many_arguments)]
pub async fn serve(
    listener: UnixListener,
    policy: RolePolicy,
    snapshots: watch::Receiver<Snapshot>,
    commands: mpsc::Sender<Command>,
    snapshot_period: Duration,
    max_connections: usize,
    mut shutdown: Shutdown,
) {
    let open = Arc::new(AtomicUsize::new(0));
    let mut refusals = Refusals::default();
    loop {
        tokio::select! {
            _ = shutdown.recv() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    if open.load(Ordering::Relaxed) >= max_connections {
                        refusals.refused(max_connections, crate::util::clock::now());
                        // Best effort, never waiting on the refused peer.
                        let msg = error_line(&format!(
                            "the service has {max_connections} control connections open (service.max_connections): close one and retry"
                        ));
                        let _ = stream.try_write(msg.as_bytes());
                        continue;
                    }
                    open.fetch_add(1, Ordering::Relaxed);
                    let conn = Connection {
                        policy: policy.clone(),
                        snapshots: snapshots.clone(),
                        commands: commands.clone(),
                        snapshot_period,
                        shutdown: shutdown.clone(),
                        _open: OpenGuard(open.clone()),
                    };
                    tokio::spawn(conn.run(stream));
                }
                Err(e) => {
                    tracing::warn!("control socket accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }
    }
}

/// Counts refused connections and logs them, at most every [`REFUSAL_LOG_EVERY`].
#[derive(Default)]
struct Refusals {
    since_log: u64,
    last_log: Option<Instant>,
}

impl Refusals {
    fn refused(&mut self, limit: usize, now: Instant) {
        self.since_log += 1;
        if self
            .last_log
            .is_none_or(|t| now.saturating_duration_since(t) >= REFUSAL_LOG_EVERY)
        {
            tracing::warn!(
                refused = self.since_log,
                "control socket: refused a connection: {limit} are open (service.max_connections)"
            );
            self.since_log = 0;
            self.last_log = Some(now);
        }
    }
}

/// One open connection in the count, for as long as it lives.
struct OpenGuard(Arc<AtomicUsize>);

impl Drop for OpenGuard {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

struct Connection {
    policy: RolePolicy,
    snapshots: watch::Receiver<Snapshot>,
    commands: mpsc::Sender<Command>,
    snapshot_period: Duration,
    shutdown: Shutdown,
    /// Counted while the connection lives.
    _open: OpenGuard,
}

fn reply_line(v: &serde_json::Value) -> String {
    let mut s = v.to_string();
    s.push('\n');
    s
}

fn error_line(msg: &str) -> String {
    reply_line(&serde_json::json!({"ok": false, "error": msg}))
}

impl Connection {
    async fn run(mut self, stream: UnixStream) {
        let peer = match stream.peer_cred() {
            Ok(c) => self.policy.peer(c.uid(), c.gid(), c.pid()).await,
            Err(e) => {
                tracing::warn!("control: no peer credentials: {e}");
                return;
            }
        };
        let (rd, mut wr) = stream.into_split();
        let mut lines = BufReader::new(rd);
        let mut buf = Vec::new();
        let mut line_no = 0usize;
        loop {
            buf.clear();
            let mut limited = (&mut lines).take(MAX_LINE as u64 + 1);
            let n = tokio::select! {
                _ = self.shutdown.recv() => return,
                n = limited.read_until(b'\n', &mut buf) => n,
            };
            match n {
                Ok(0) | Err(_) => return,
                Ok(_) => {}
            }
            line_no += 1;
            if buf.len() > MAX_LINE {
                let _ = wr
                    .write_all(
                        error_line(&format!("line {line_no}: longer than {MAX_LINE} bytes"))
                            .as_bytes(),
                    )
                    .await;
                return;
            }
            let text = match std::str::from_utf8(&buf) {
                Ok(t) => t.trim(),
                Err(e) => {
                    let msg = format!(
                        "line {line_no}: not UTF-8 text (byte {} is not); requests are JSON like {{\"cmd\":\"status\"}}",
                        e.valid_up_to() + 1
                    );
                    if wr.write_all(error_line(&msg).as_bytes()).await.is_err() {
                        return;
                    }
                    continue;
                }
            };
            if text.is_empty() {
                continue;
            }
            let request: Request = match serde_json::from_str(text) {
                Ok(r) => r,
                Err(e) => {
                    let msg = format!(
                        "line {line_no}: {e}; requests are JSON like {{\"cmd\":\"status\"}}"
                    );
                    if wr.write_all(error_line(&msg).as_bytes()).await.is_err() {
                        return;
                    }
                    continue;
                }
            };
            if peer.role.is_none_or(|r| r < request.needs()) {
                let (role, group, key) = if request.needs() == Role::Operator {
                    ("operator", &self.policy.operator_group, "operator_group")
                } else {
                    ("viewer", &self.policy.viewer_group, "viewer_group")
                };
                let msg = format!(
                    "user {} (uid {}) may not {}: it needs the {role} role, membership of group {group} (service.{key}); an administrator adds it with: adduser {} {group}",
                    peer.user,
                    peer.uid,
                    serde_json::to_value(&request)
                        .ok()
                        .and_then(|v| v.get("cmd").and_then(|c| c.as_str().map(str::to_string)))
                        .unwrap_or_default(),
                    peer.user,
                );
                if wr.write_all(error_line(&msg).as_bytes()).await.is_err() {
                    return;
                }
                continue;
            }
            // The ranges once the role allows the request (a peer without it is told so, not
            // what else is wrong with it); here for what this task answers itself, and where
            // the request is audited for the rest (the core, the tables task), so that a
            // refused request is recorded as refused.
            if matches!(request, Request::Status | Request::Subscribe { .. })
                && let Err(e) = request.check()
            {
                let msg = format!("line {line_no}: {e}");
                if wr.write_all(error_line(&msg).as_bytes()).await.is_err() {
                    return;
                }
                continue;
            }
            let out = match request {
                Request::Status => {
                    // Who asked and with which role, so a client (the console) can show a
                    // read-only mode before anything is refused.
                    let snap = self.snapshots.borrow().clone();
                    reply_line(
                        &serde_json::json!({"ok": true, "snapshot": snap, "user": peer.user, "role": peer.role}),
                    )
                }
                Request::Subscribe { hz } => {
                    // `hz` is in range (`Request::check`).
                    let period = hz
                        .and_then(|h| crate::config::SNAPSHOT_HZ.period(h).ok())
                        .unwrap_or(self.snapshot_period);
                    self.stream_snapshots(&mut wr, period).await;
                    return;
                }
                request => {
                    let (tx, rx) = oneshot::channel();
                    let cmd = Command {
                        request,
                        peer: peer.clone(),
                        reply: tx,
                    };
                    if self.commands.send(cmd).await.is_err() {
                        error_line("the service is shutting down")
                    } else {
                        match tokio::time::timeout(Duration::from_secs(60), rx).await {
                            Ok(Ok(Ok(v))) => {
                                reply_line(&serde_json::json!({"ok": true, "result": v}))
                            }
                            Ok(Ok(Err(e))) => error_line(&e),
                            Ok(Err(_)) => error_line("the service dropped the request"),
                            Err(_) => error_line("no answer within 60 s"),
                        }
                    }
                }
            };
            if wr.write_all(out.as_bytes()).await.is_err() {
                return;
            }
        }
    }

    async fn stream_snapshots(
        &mut self,
        wr: &mut tokio::net::unix::OwnedWriteHalf,
        period: Duration,
    ) {
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                _ = self.shutdown.recv() => return,
                _ = tick.tick() => {
                    let snap = self.snapshots.borrow().clone();
                    let line = reply_line(&serde_json::json!({"snapshot": snap}));
                    if wr.write_all(line.as_bytes()).await.is_err() {
                        return;
                    }
                }
            }
        }
    }
}

/// A client of the control API (for `axiscomp status` and the console).
pub struct Client {
    lines: tokio::io::Lines<BufReader<tokio::net::unix::OwnedReadHalf>>,
    wr: tokio::net::unix::OwnedWriteHalf,
    pub path: PathBuf,
}

/// Why a control client failed.
#[derive(Debug, Error)]
pub enum ClientError {
    #[error(
        "cannot connect to {path}: {source}; is the service running (systemctl status axiscomp)?"
    )]
    Connect {
        path: String,
        source: std::io::Error,
    },
    #[error(
        "cannot connect to {path}: permission denied; only the service's viewer and operator groups may (axiscomp-view and axiscomp as installed): ask an administrator to add you to one"
    )]
    Forbidden { path: String },
    #[error("control connection: {0}")]
    Io(#[from] std::io::Error),
    #[error("the service closed the connection")]
    Closed,
    #[error("bad reply from the service: {0}")]
    Reply(String),
    #[error("{0}")]
    Refused(String),
}

impl Client {
    /// Connect to the socket at `path`.
    pub async fn connect(path: &Path) -> Result<Client, ClientError> {
        let s = UnixStream::connect(path).await.map_err(|source| {
            let path = path.display().to_string();
            if source.kind() == std::io::ErrorKind::PermissionDenied {
                ClientError::Forbidden { path }
            } else {
                ClientError::Connect { path, source }
            }
        })?;
        let (rd, wr) = s.into_split();
        Ok(Client {
            lines: BufReader::new(rd).lines(),
            wr,
            path: path.to_path_buf(),
        })
    }

    /// Whether the service has closed this connection while it sat idle (a restarted
    /// service, an idle timeout): its end of the socket reads end-of-file, or a line nobody
    /// asked for waits in it. A request connection is only read for the reply to its own
    /// request, so either means the next request would go nowhere: open a new one instead.
    pub fn closed_by_peer(&mut self) -> bool {
        let buffered = self.lines.get_mut();
        if !buffered.buffer().is_empty() {
            return true;
        }
        let mut probe = [0u8; 1];
        match buffered.get_ref().try_read(&mut probe) {
            // End of file, or bytes nobody asked for.
            Ok(_) => true,
            Err(e) => e.kind() != std::io::ErrorKind::WouldBlock,
        }
    }

    /// Send one request line (its reply is read with [`next_value`](Self::next_value)).
    pub async fn send(&mut self, r: &Request) -> Result<(), ClientError> {
        let mut s = serde_json::to_string(r).map_err(|e| ClientError::Reply(e.to_string()))?;
        s.push('\n');
        self.wr.write_all(s.as_bytes()).await?;
        Ok(())
    }

    /// The next line from the service, as JSON.
    pub async fn next_value(&mut self) -> Result<serde_json::Value, ClientError> {
        let line = self.lines.next_line().await?.ok_or(ClientError::Closed)?;
        serde_json::from_str(&line).map_err(|e| ClientError::Reply(format!("{e}: {line}")))
    }

    /// Send a request and return its `result` (or `snapshot` for status).
    pub async fn request(&mut self, r: &Request) -> Result<serde_json::Value, ClientError> {
        self.send(r).await?;
        let v = self.next_value().await?;
        if v.get("ok").and_then(|o| o.as_bool()) == Some(true) {
            Ok(v.get("result")
                .or_else(|| v.get("snapshot"))
                .cloned()
                .unwrap_or(serde_json::Value::Null))
        } else {
            Err(ClientError::Refused(
                v.get("error")
                    .and_then(|e| e.as_str())
                    .unwrap_or("refused")
                    .to_string(),
            ))
        }
    }

    /// The current snapshot.
    pub async fn status(&mut self) -> Result<Snapshot, ClientError> {
        let v = self.request(&Request::Status).await?;
        serde_json::from_value(v).map_err(|e| ClientError::Reply(e.to_string()))
    }

    /// Start a snapshot stream; then call `next_snapshot`.
    pub async fn subscribe(&mut self, hz: Option<f64>) -> Result<(), ClientError> {
        self.send(&Request::Subscribe { hz }).await
    }

    /// The next snapshot of a stream.
    pub async fn next_snapshot(&mut self) -> Result<Snapshot, ClientError> {
        let v = self.next_value().await?;
        if let Some(err) = v.get("error").and_then(|e| e.as_str()) {
            return Err(ClientError::Refused(err.to_string()));
        }
        let snap = v
            .get("snapshot")
            .cloned()
            .ok_or_else(|| ClientError::Reply(v.to_string()))?;
        serde_json::from_value(snap).map_err(|e| ClientError::Reply(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn socket_round_trip_and_refusal() {
        let dir = std::env::temp_dir().join(format!("axiscomp-ctl-{}", std::process::id()));
        let path = dir.join("control.sock");
        let listener = bind(&path).unwrap();
        let (snap_tx, snap_rx) = watch::channel(Snapshot {
            unix_us: 42,
            ..Snapshot::default()
        });
        let (cmd_tx, mut cmd_rx) = mpsc::channel::<Command>(4);
        let (trigger, shutdown) = super::super::shutdown::channel();
        // As the service's own user we are an operator (refusals are tested across users in
        // the integration tests).
        let me = RolePolicy::from_names("no-such-group-a", "no-such-group-b");
        tokio::spawn(serve(
            listener,
            me,
            snap_rx,
            cmd_tx,
            Duration::from_millis(20),
            2,
            shutdown.clone(),
        ));
        tokio::spawn(async move {
            while let Some(c) = cmd_rx.recv().await {
                let _ = c
                    .reply
                    .send(Ok(serde_json::json!({"done": format!("{:?}", c.request)})));
            }
        });
        let mut c = Client::connect(&path).await.unwrap();
        assert_eq!(c.status().await.unwrap().unix_us, 42);
        let v = c.request(&Request::Zero).await.unwrap();
        assert_eq!(v["done"], "Zero");
        // A malformed line gets an error naming the line, and the connection stays usable.
        c.wr.write_all(b"{\"cmd\":\"fly\"}\n").await.unwrap();
        let v = c.next_value().await.unwrap();
        assert!(v["error"].as_str().unwrap().starts_with("line 3:"), "{v}");
        // A line that is not JSON, and one that is not even text: an error each, not silence.
        c.wr.write_all(b"hello\n").await.unwrap();
        let v = c.next_value().await.unwrap();
        let e = v["error"].as_str().unwrap();
        assert!(
            e.starts_with("line 4: expected value")
                && e.ends_with(r#"requests are JSON like {"cmd":"status"}"#),
            "{v}"
        );
        c.wr.write_all(b"{\"cmd\":\xff\xfe}\n").await.unwrap();
        let v = c.next_value().await.unwrap();
        assert_eq!(
            v["error"],
            r#"line 5: not UTF-8 text (byte 8 is not); requests are JSON like {"cmd":"status"}"#
        );
        assert_eq!(v["ok"], false);
        // A number out of range is refused naming the field and the range, and the
        // connection stays usable (a subscribe at 1e-300 Hz panicked its task).
        c.wr.write_all(b"{\"cmd\":\"subscribe\",\"hz\":1e-300}\n")
            .await
            .unwrap();
        let v = c.next_value().await.unwrap();
        assert_eq!(
            v["error"],
            r#"line 6: "hz": 1e-300 Hz is out of range: use 0.1 to 100 Hz"#
        );
        assert_eq!(c.status().await.unwrap().unix_us, 42);
        // Two connections at most here: a third is refused with a reason, and admitted once
        // one closes.
        let c2 = Client::connect(&path).await.unwrap();
        let mut c3 = Client::connect(&path).await.unwrap();
        let v = c3.next_value().await.unwrap();
        assert_eq!(
            v["error"],
            "the service has 2 control connections open (service.max_connections): close one and retry"
        );
        drop((c2, c3));
        let mut c4 = None;
        for _ in 0..50 {
            tokio::time::sleep(Duration::from_millis(10)).await;
            let mut c = Client::connect(&path).await.unwrap();
            if c.status().await.is_ok() {
                c4 = Some(c);
                break;
            }
        }
        assert!(c4.is_some(), "admitted again once a connection closed");
        drop(c4);
        c.subscribe(Some(50.0)).await.unwrap();
        snap_tx.send_modify(|s| s.unix_us = 7);
        let mut seen = false;
        for _ in 0..20 {
            if c.next_snapshot().await.unwrap().unix_us == 7 {
                seen = true;
                break;
            }
        }
        assert!(seen);
        trigger.trigger();
        let _ = std::fs::remove_dir_all(&dir);
    }
}
