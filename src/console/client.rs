//! The console's control-API client (DESIGN §8): newline-delimited JSON over the service's Unix
//! socket. Two connections, because `subscribe` turns a connection into a one-way stream: one
//! streams snapshots, the other carries requests one at a time. Both reconnect with backoff
//! when the service restarts; the console sees everything as [`LinkEvent`]s.
//!
//! Requests are never re-sent after a lost connection (a start or a jog must not happen twice):
//! the reply says the link failed, and the operator decides.

use crate::service::api::Request;
use crate::service::api::snapshot::Snapshot;
use crate::service::control;
use std::path::{Path, PathBuf};
use std::time::Duration;
use thiserror::Error;
use tokio::sync::mpsc;

/// Longest wait for one reply; the service answers within 60 s or says it did not.
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(70);

/// Why a request or the stream failed. Cloneable: it travels to the app as text and kind.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum ClientError {
    #[error(
        "cannot connect to {path}: {reason}; is the service running (systemctl status axiscomp)?"
    )]
    Connect { path: String, reason: String },
    /// The socket refused this user (not in the viewer or operator group).
    #[error("{0}")]
    Forbidden(String),
    #[error("control connection: {0}")]
    Io(String),
    #[error("the service closed the connection")]
    Closed,
    #[error("no reply within {}", crate::util::time::span(*.0))]
    Timeout(Duration),
    #[error("bad reply from the service: {0}")]
    Reply(String),
    /// The service answered `{"ok":false,"error":...}`: the text is the service's.
    #[error("{0}")]
    Refused(String),
}

impl ClientError {
    /// Whether the connection is unusable after this error (a refusal leaves it usable).
    pub fn breaks_connection(&self) -> bool {
        !matches!(self, ClientError::Refused(_))
    }

    /// Whether the service refused because the peer lacks the operator role.
    pub fn is_role_refusal(&self) -> bool {
        matches!(self, ClientError::Refused(t) if t.contains("needs the operator role"))
    }
}

impl From<control::ClientError> for ClientError {
    fn from(e: control::ClientError) -> Self {
        use control::ClientError as C;
        match e {
            C::Connect { path, source } => ClientError::Connect {
                path,
                reason: source.to_string(),
            },
            e @ C::Forbidden { .. } => ClientError::Forbidden(e.to_string()),
            C::Io(e) => ClientError::Io(e.to_string()),
            C::Closed => ClientError::Closed,
            C::Reply(r) => ClientError::Reply(r),
            C::Refused(r) => ClientError::Refused(r),
        }
    }
}

/// What the peer may do, as the service's `status` reply says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PeerRole {
    Viewer,
    Operator,
}

/// Who the service says we are (`status` reply); `None` from a service that does not say.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Identity {
    pub user: Option<String>,
    pub role: Option<PeerRole>,
}

/// Everything the client tells the console.
#[derive(Clone, Debug, PartialEq)]
pub enum LinkEvent {
    /// The snapshot stream is up (again).
    Connected(Identity),
    Snapshot(Box<Snapshot>),
    /// The snapshot stream is down; the next attempt is in `retry_in`.
    Down {
        error: ClientError,
        retry_in: Duration,
    },
    /// The reply to request `id`: its `result` (or the whole reply for `status`).
    Reply {
        id: u64,
        result: Result<serde_json::Value, ClientError>,
    },
}

pub use crate::util::backoff::Backoff;

/// One connection to the control socket (the service's own client underneath).
pub struct Conn(control::Client);

fn identity_of(reply: &serde_json::Value) -> Identity {
    Identity {
        user: reply
            .get("user")
            .and_then(|u| u.as_str())
            .map(str::to_string),
        role: match reply.get("role").and_then(|r| r.as_str()) {
            Some("operator") => Some(PeerRole::Operator),
            Some("viewer") => Some(PeerRole::Viewer),
            _ => None,
        },
    }
}

fn snapshot_of(v: serde_json::Value) -> Result<Snapshot, ClientError> {
    serde_json::from_value(v).map_err(|e| ClientError::Reply(format!("snapshot: {e}")))
}

impl Conn {
    pub async fn connect(path: &Path) -> Result<Conn, ClientError> {
        Ok(Conn(control::Client::connect(path).await?))
    }

    /// Whether the service closed this connection while it was idle (see
    /// [`control::Client::closed_by_peer`]).
    fn closed_by_peer(&mut self) -> bool {
        self.0.closed_by_peer()
    }

    async fn send(&mut self, r: &Request) -> Result<(), ClientError> {
        Ok(self.0.send(r).await?)
    }

    async fn next_value(&mut self) -> Result<serde_json::Value, ClientError> {
        Ok(self.0.next_value().await?)
    }

    /// Send `r` and wait for its reply line: the whole reply when `ok`, else `Refused`.
    pub async fn call(&mut self, r: &Request) -> Result<serde_json::Value, ClientError> {
        let exchange = async {
            self.send(r).await?;
            self.next_value().await
        };
        let v = tokio::time::timeout(REPLY_TIMEOUT, exchange)
            .await
            .map_err(|_| ClientError::Timeout(REPLY_TIMEOUT))??;
        if v.get("ok").and_then(|o| o.as_bool()) == Some(true) {
            Ok(v)
        } else {
            Err(ClientError::Refused(
                v.get("error")
                    .and_then(|e| e.as_str())
                    .unwrap_or("refused without a reason")
                    .to_string(),
            ))
        }
    }

    /// `status`: the current snapshot and who we are.
    pub async fn hello(&mut self) -> Result<(Identity, Snapshot), ClientError> {
        let mut v = self.call(&Request::Status).await?;
        let id = identity_of(&v);
        let snap = snapshot_of(v.get_mut("snapshot").map(|s| s.take()).unwrap_or_default())?;
        Ok((id, snap))
    }

    /// Turn the connection into a snapshot stream at `hz`.
    pub async fn subscribe(mut self, hz: f64) -> Result<SnapshotStream, ClientError> {
        self.send(&Request::Subscribe { hz: Some(hz) }).await?;
        Ok(SnapshotStream { conn: self })
    }
}

/// A `subscribe` connection.
pub struct SnapshotStream {
    conn: Conn,
}

impl SnapshotStream {
    /// The next snapshot; an error line or a malformed line ends the stream.
    pub async fn next(&mut self) -> Result<Snapshot, ClientError> {
        let mut v = self.conn.next_value().await?;
        if let Some(err) = v.get("error").and_then(|e| e.as_str()) {
            return Err(ClientError::Refused(err.to_string()));
        }
        match v.get_mut("snapshot") {
            Some(s) => snapshot_of(s.take()),
            None => Err(ClientError::Reply(v.to_string())),
        }
    }
}

/// How the client behaves.
#[derive(Clone, Debug)]
pub struct ClientOptions {
    pub socket: PathBuf,
    /// Snapshot rate asked of the service.
    pub hz: f64,
    pub backoff_min: Duration,
    pub backoff_max: Duration,
}

impl ClientOptions {
    pub fn new(socket: PathBuf) -> Self {
        ClientOptions {
            socket,
            hz: 10.0,
            backoff_min: Duration::from_millis(100),
            backoff_max: Duration::from_secs(2),
        }
    }
}

/// The running client: send requests with [`Client::send`], read [`LinkEvent`]s from
/// `events`. Dropping it stops both tasks.
pub struct Client {
    requests: mpsc::Sender<(u64, Request)>,
    pub events: mpsc::Receiver<LinkEvent>,
    tasks: [tokio::task::JoinHandle<()>; 2],
}

impl Drop for Client {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

impl Client {
    /// Start the snapshot and request tasks (inside a tokio runtime).
    pub fn spawn(opts: ClientOptions) -> Client {
        let (ev_tx, events) = mpsc::channel(64);
        let (requests, req_rx) = mpsc::channel(16);
        let stream = tokio::spawn(stream_task(opts.clone(), ev_tx.clone()));
        let calls = tokio::spawn(request_task(opts.socket, req_rx, ev_tx));
        Client {
            requests,
            events,
            tasks: [stream, calls],
        }
    }

    /// Queue request `id`; its reply arrives as [`LinkEvent::Reply`]. Fails only when the
    /// request task has ended.
    pub async fn send(&self, id: u64, request: Request) -> Result<(), ClientError> {
        self.requests
            .send((id, request))
            .await
            .map_err(|_| ClientError::Closed)
    }
}

/// Keep a snapshot stream up: connect, `status` (identity), `subscribe`, forward; on any
/// failure report it and retry after the backoff.
async fn stream_task(opts: ClientOptions, tx: mpsc::Sender<LinkEvent>) {
    let mut backoff = Backoff::new(opts.backoff_min, opts.backoff_max);
    loop {
        let error = match stream_session(&opts, &tx, &mut backoff).await {
            Ok(()) => return, // the console went away
            Err(e) => e,
        };
        let retry_in = backoff.next_delay();
        if tx.send(LinkEvent::Down { error, retry_in }).await.is_err() {
            return;
        }
        tokio::time::sleep(retry_in).await;
    }
}

/// One connection's life; `Ok` only when the console stopped listening.
async fn stream_session(
    opts: &ClientOptions,
    tx: &mpsc::Sender<LinkEvent>,
    backoff: &mut Backoff,
) -> Result<(), ClientError> {
    let mut conn = Conn::connect(&opts.socket).await?;
    let (identity, first) = conn.hello().await?;
    let mut stream = conn.subscribe(opts.hz).await?;
    backoff.reset();
    if tx.send(LinkEvent::Connected(identity)).await.is_err()
        || tx.send(LinkEvent::Snapshot(Box::new(first))).await.is_err()
    {
        return Ok(());
    }
    loop {
        let snap = stream.next().await?;
        if tx.send(LinkEvent::Snapshot(Box::new(snap))).await.is_err() {
            return Ok(());
        }
    }
}

/// Carry requests one at a time on a connection opened on demand; a broken connection is
/// dropped and the next request opens a new one. A connection the service closed while it
/// sat idle (the service restarted since the last request) is replaced before the request
/// goes out: the request was never sent on it, so this is not a re-send.
async fn request_task(
    socket: PathBuf,
    mut rx: mpsc::Receiver<(u64, Request)>,
    tx: mpsc::Sender<LinkEvent>,
) {
    let mut conn: Option<Conn> = None;
    while let Some((id, request)) = rx.recv().await {
        let result: Result<serde_json::Value, ClientError> = async {
            if conn.as_mut().is_some_and(Conn::closed_by_peer) {
                conn = None;
            }
            let c = match conn.as_mut() {
                Some(c) => c,
                None => conn.insert(Conn::connect(&socket).await?),
            };
            let mut v = c.call(&request).await?;
            // `result` for commands, the whole reply (snapshot, user, role) for `status`.
            Ok(match v.get_mut("result") {
                Some(r) => r.take(),
                None => v,
            })
        }
        .await;
        if let Err(e) = &result
            && e.breaks_connection()
        {
            conn = None;
        }
        if tx.send(LinkEvent::Reply { id, result }).await.is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_from_the_status_reply() {
        let v = serde_json::json!({"ok": true, "snapshot": {}, "user": "ana", "role": "viewer"});
        assert_eq!(
            identity_of(&v),
            Identity {
                user: Some("ana".into()),
                role: Some(PeerRole::Viewer)
            }
        );
        // An older service says nothing: unknown until a refusal tells.
        assert_eq!(
            identity_of(&serde_json::json!({"ok": true})),
            Identity::default()
        );
    }

    #[test]
    fn refusals_keep_the_connection_and_name_the_role() {
        let r = ClientError::Refused(
            "user ana (uid 1001) may not zero: it needs the operator role (operator_group group)"
                .into(),
        );
        assert!(!r.breaks_connection());
        assert!(r.is_role_refusal());
        assert!(ClientError::Closed.breaks_connection());
    }

    #[tokio::test]
    async fn reconnects_after_the_service_restarts() {
        use crate::service::control::{Command, bind, serve};
        use crate::service::peer::RolePolicy;
        use tokio::sync::watch;
        let dir = std::env::temp_dir().join(format!("axiscomp-console-{}", std::process::id()));
        let path = dir.join("control.sock");
        let mut opts = ClientOptions::new(path.clone());
        opts.hz = 50.0;
        opts.backoff_max = Duration::from_millis(200);
        let mut client = Client::spawn(opts);
        // Nobody listens yet: a Down event with the connect error.
        match client.events.recv().await {
            Some(LinkEvent::Down { error, .. }) => {
                assert!(matches!(error, ClientError::Connect { .. }), "{error}")
            }
            other => panic!("{other:?}"),
        }
        let start = |unix_us: i64| {
            let listener = bind(&path).expect("bind");
            let (snap_tx, snap_rx) = watch::channel(Snapshot {
                unix_us,
                ..Snapshot::default()
            });
            let (cmd_tx, mut cmd_rx) = mpsc::channel::<Command>(4);
            let (trigger, shutdown) = crate::service::shutdown::channel();
            let policy = RolePolicy::from_names("no-such-group-a", "no-such-group-b");
            tokio::spawn(serve(
                listener,
                policy,
                snap_rx,
                cmd_tx,
                Duration::from_millis(20),
                64,
                shutdown,
            ));
            tokio::spawn(async move {
                while let Some(c) = cmd_rx.recv().await {
                    let _ = c.reply.send(Ok(serde_json::json!({"echo": true})));
                }
            });
            (trigger, snap_tx)
        };
        let wait_snapshot = async |client: &mut Client, unix_us: i64| loop {
            match client.events.recv().await {
                Some(LinkEvent::Snapshot(s)) if s.unix_us == unix_us => return,
                Some(_) => {}
                None => panic!("client ended"),
            }
        };
        let (trigger, _snaps) = start(1);
        let within = Duration::from_secs(5);
        tokio::time::timeout(within, wait_snapshot(&mut client, 1))
            .await
            .expect("first service");
        let reply = async |client: &mut Client, id: u64| {
            client.send(id, Request::Zero).await.expect("send");
            let got = tokio::time::timeout(within, async {
                loop {
                    if let Some(LinkEvent::Reply { id, result }) = client.events.recv().await {
                        return (id, result);
                    }
                }
            });
            got.await.expect("a reply")
        };
        assert_eq!(
            reply(&mut client, 7).await,
            (7, Ok(serde_json::json!({"echo": true})))
        );
        // The service goes away and comes back: the stream reconnects by itself.
        trigger.trigger();
        tokio::time::sleep(Duration::from_millis(100)).await;
        let (trigger, _snaps) = start(2);
        tokio::time::timeout(within, wait_snapshot(&mut client, 2))
            .await
            .expect("second service");
        // The first request after the restart reaches the new service: the request
        // connection the old one closed is not used for it (it answered 'control connection:
        // Broken pipe (os error 32)' under a connected header).
        assert_eq!(
            reply(&mut client, 8).await,
            (8, Ok(serde_json::json!({"echo": true})))
        );
        trigger.trigger();
        let _ = std::fs::remove_dir_all(&dir);
    }
}
