//! The control API (DESIGN §8): a Unix socket, newline-delimited JSON. One request per line,
//! one response per line (`{"ok":true,...}` or `{"ok":false,"error":"..."}`); `subscribe` turns
//! the connection into a stream of snapshots (`{"snapshot":{...}}` per line).
//!
//! Viewing (`status`, `subscribe`, `run_status`, `runs`, `run_result`, `audit`,
//! `table_list`, `table_status`) needs the viewer role; anything that changes state needs the operator role, and the service writes it
//! to the audit log; the `status` reply names the peer's `user` and `role`. Roles come from the peer's credentials (`peer`). The socket file
//! admits only its owner and the two role groups ([`open_to_roles`]): others are refused on connect
//! by the kernel; within, access is decided per request, so a viewer's refusal can say why.

use super::peer::{Peer, Role, RolePolicy};
use super::shutdown::Shutdown;
use super::snapshot::Snapshot;
use crate::track::Strategy;
use serde::{Deserialize, Serialize};
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

/// What the follower should do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FollowerAction {
    Home,
    Enable,
    Disable,
    /// Relative move by `mm`.
    Jog,
    /// Absolute move to `mm`.
    Move,
    Stop,
    FaultReset,
}

/// A control request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "snake_case", deny_unknown_fields)]
pub enum Request {
    /// The current snapshot.
    Status,
    /// A stream of snapshots at `hz` (default: the service's snapshot rate).
    Subscribe {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        hz: Option<f64>,
    },
    /// Command the follower.
    Follower {
        action: FollowerAction,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mm: Option<f64>,
    },
    /// Take the live errors here as the zero reference (and re-reference the stitching).
    Zero,
    /// Forget the zero reference.
    ClearZero,
    /// Set (or clear, with null) the nominal travel position the carriage is commanded to.
    Nominal { mm: Option<f64> },
    /// Switch the stitching strategy.
    Strategy { strategy: Strategy },
    /// Start an ISO 230-2 run: the plan, optionally another program dialect than configured.
    RunStart {
        plan: crate::run::PlanSpec,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        dialect: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        notes: Option<String>,
    },
    /// The active (or last) run's progress.
    RunStatus,
    /// Stop the active run (its captures stay stored).
    RunAbort,
    /// The stored runs, newest first (at most `limit`, default 50).
    Runs {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<usize>,
    },
    /// A stored run's evaluation: the six errors per direction and the ISO figures
    /// (`run_id`, or the newest finished run).
    RunResult {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        run_id: Option<i64>,
    },
    /// The newest entries of the audit log (every operator request, who and when), newest
    /// first (at most `limit`, default 50).
    Audit {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<u32>,
    },
    /// The calibration in use, the one waiting for a decision, whether a fit runs.
    Calibration,
    /// Fit the pose set at `poses` (a CSV on the service's host, `calibrate fit`'s input
    /// format); the result waits for accept or reject.
    CalibrationFit { poses: String },
    /// Store the waiting calibration and decouple with it from now on (the zero is cleared).
    /// A calibration with plausibility concerns (`calibrate::plausible`) is refused unless
    /// `force` is set.
    CalibrationAccept {
        #[serde(default)]
        force: bool,
    },
    /// Drop the waiting calibration.
    CalibrationReject,
    /// Calibrate with the hexapod in the loop (`[hexapod]`): the plan CSV `plan` on the
    /// service's host, or `poses` poses generated over the operating window (200); the run
    /// directory `out` (default: `hexapod-run` in the state directory) resumes when it holds
    /// poses of the same plan. The fit then waits for accept or reject.
    HexapodStart {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        plan: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        poses: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        out: Option<String>,
    },
    /// Where the hexapod run is (`service::hexapod_run::RunView`).
    HexapodStatus,
    /// Halt the hexapod and end its run before the next pose (start again to resume).
    HexapodStop,
    /// The stored compensation tables, newest first (at most `limit`, default 50), each with
    /// its latest publication.
    TableList {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<usize>,
    },
    /// Evaluate stored run `run_id`, build its compensation tables for the configured CNC map
    /// and store them: their ids and a summary.
    TableGenerate { run_id: i64 },
    /// Publish stored table `table_id` to the PLC (push, or serve it for pull); refused unless
    /// `confirm` is true. The reply says committed (with the sequence), rejected (with the
    /// PLC's code) or failed (with the reason).
    TablePublish {
        table_id: i64,
        #[serde(default)]
        confirm: bool,
    },
    /// What the PLC holds now, read back and compared with the store.
    TableStatus,
    /// Beam alignment: read the spots as a station with the carriage at rest at `at_mm` (the
    /// measured position when left out).
    AlignRead {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        at_mm: Option<f64>,
    },
    /// What the alignment target in front of PSD `psd` (1..3) shows at the last station (mm),
    /// where the spot is off the PSD.
    AlignTarget { psd: usize, x: f64, y: f64 },
    /// The screw turns, beam angle and check over `from_mm`..`to_mm` from the stations read.
    AlignAdvice {
        from_mm: f64,
        to_mm: f64,
        /// The axis the alignment is stored for ("X" when not given).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        axis: Option<String>,
    },
    /// Forget the stations read (after turning screws, read both ends again).
    AlignClear,
    /// The follower error map in use and the stored ones; with `id`, put stored map `id` in
    /// use first (operators).
    FollowerMap {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        id: Option<i64>,
    },
    /// Import the follower encoder's calibration certificate (`path` on the service's host,
    /// or its `csv` text): stored with its map and, unless `keep_current`, applied at once
    /// (joined with the self-calibration of the map in use when it has one).
    FollowerCertificate(super::follower::CertificateImport),
    /// Map the follower by the stop-and-go self-calibration (`service::follower_map`): its
    /// part program to the CNC; at the end the map stored and put in use.
    FollowerMapStart(super::follower_map::MappingRequest),
    /// Where the follower mapping is (`service::follower_map::MappingView`).
    FollowerMapStatus,
    /// Stop the follower mapping: nothing is stored.
    FollowerMapStop,
    /// Build the follower map now from the steps so far (with a CNC the service does not
    /// drive, or when enough is enough).
    FollowerMapFinish,
    /// Read a level at stations along the follower's map (`service::follower_level`): at the
    /// end the map refitted with the stations, stored and put in use.
    FollowerLevelStart(super::follower_level::LevelRequest),
    /// Where the level stations are (`service::follower_level::LevelView`).
    FollowerLevelStatus,
    /// The level's reading (arcsec) at the station being read (`[follower] level = "manual"`).
    FollowerLevelReading {
        #[serde(default)]
        arcsec: serde_json::Value,
    },
    /// Stop the level stations: nothing is stored.
    FollowerLevelStop,
    /// Fit the map now with the stations taken (two at least).
    FollowerLevelFinish,
}

impl Request {
    /// The role the request needs.
    pub fn needs(&self) -> Role {
        match self {
            Request::Status
            | Request::Subscribe { .. }
            | Request::RunStatus
            | Request::Runs { .. }
            | Request::RunResult { .. }
            | Request::Audit { .. }
            | Request::Calibration
            | Request::HexapodStatus
            | Request::TableList { .. }
            | Request::TableStatus
            | Request::FollowerMap { id: None }
            | Request::FollowerMapStatus
            | Request::FollowerLevelStatus => Role::Viewer,
            _ => Role::Operator,
        }
    }

    /// Every number of the request within its range, or the first that is not, named with
    /// the range (DESIGN §8: bad input gets a clear error that names the input and what to
    /// do). Checked once, right after the line parses, so nothing downstream sees a NaN, an
    /// infinity or a count no machine has; how the numbers fit together (a span's ends, a
    /// plan's targets for its length) is checked where they are used.
    pub fn check(&self) -> Result<(), String> {
        use crate::util::range::{POSITION_MM, Range, field, int_field};
        // Stored runs, tables and maps are numbered from 1.
        let id = |name: &str, v: Option<i64>| match v {
            Some(v) if v < 1 => Err(format!(
                "\"{name}\": {v} is not an id: give a stored one's, 1 or more"
            )),
            _ => Ok(()),
        };
        const LIMIT: usize = 10_000;
        match self {
            Request::Subscribe { hz } => field("hz", *hz, crate::config::SNAPSHOT_HZ),
            Request::Follower { mm, .. } | Request::Nominal { mm } => field("mm", *mm, POSITION_MM),
            Request::RunStart { plan, .. } => plan.check().map_err(|e| e.to_string()),
            Request::Runs { limit } | Request::TableList { limit } => {
                int_field("limit", *limit, 1, LIMIT)
            }
            Request::Audit { limit } => int_field("limit", *limit, 1, LIMIT as u32),
            Request::RunResult { run_id } => id("run_id", *run_id),
            Request::TableGenerate { run_id } => id("run_id", Some(*run_id)),
            Request::TablePublish { table_id, .. } => id("table_id", Some(*table_id)),
            Request::FollowerMap { id: map } => id("id", *map),
            Request::HexapodStart { poses, .. } => {
                use super::hexapod_run::{MAX_POSES, MIN_POSES};
                int_field("poses", *poses, MIN_POSES, MAX_POSES)
            }
            Request::AlignRead { at_mm } => field("at_mm", *at_mm, POSITION_MM),
            Request::AlignTarget { psd, x, y } => {
                // What a target in front of a PSD shows: within a hand's width of its centre.
                let target = Range::symmetric(100.0, "mm");
                int_field("psd", Some(*psd), 1, 3)?;
                field("x", Some(*x), target)?;
                field("y", Some(*y), target)
            }
            Request::AlignAdvice { from_mm, to_mm, .. } => {
                field("from_mm", Some(*from_mm), POSITION_MM)?;
                field("to_mm", Some(*to_mm), POSITION_MM)
            }
            Request::FollowerMapStart(m) => m.check(),
            Request::FollowerLevelStart(l) => l.check(),
            Request::FollowerLevelReading { arcsec } if !arcsec.is_null() => {
                super::follower_level::typed_reading(arcsec).map(drop)
            }
            // No numbers (a new request with numbers must be added above).
            Request::Status
            | Request::Zero
            | Request::ClearZero
            | Request::Strategy { .. }
            | Request::RunStatus
            | Request::RunAbort
            | Request::Calibration
            | Request::CalibrationFit { .. }
            | Request::CalibrationAccept { .. }
            | Request::CalibrationReject
            | Request::HexapodStatus
            | Request::HexapodStop
            | Request::TableStatus
            | Request::AlignClear
            | Request::FollowerCertificate(_)
            | Request::FollowerMapStatus
            | Request::FollowerMapStop
            | Request::FollowerMapFinish
            | Request::FollowerLevelStatus
            | Request::FollowerLevelReading { .. }
            | Request::FollowerLevelStop
            | Request::FollowerLevelFinish => Ok(()),
        }
    }

    /// Whether the tables task answers it (`service::tables`), not the core.
    pub fn is_table(&self) -> bool {
        matches!(
            self,
            Request::TableList { .. }
                | Request::TableGenerate { .. }
                | Request::TablePublish { .. }
                | Request::TableStatus
        )
    }
}

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
            Ok(c) => self.policy.peer(c.uid(), c.gid(), c.pid()),
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
            if let Err(e) = request.check() {
                let msg = format!("line {line_no}: {e}");
                if wr.write_all(error_line(&msg).as_bytes()).await.is_err() {
                    return;
                }
                continue;
            }
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

    #[test]
    fn requests_parse_and_name_their_role() {
        let r: Request =
            serde_json::from_str(r#"{"cmd":"follower","action":"jog","mm":0.5}"#).unwrap();
        assert_eq!(
            r,
            Request::Follower {
                action: FollowerAction::Jog,
                mm: Some(0.5)
            }
        );
        assert_eq!(r.needs(), Role::Operator);
        let r: Request = serde_json::from_str(r#"{"cmd":"status"}"#).unwrap();
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request = serde_json::from_str(r#"{"cmd":"run_result","run_id":3}"#).unwrap();
        assert_eq!(r, Request::RunResult { run_id: Some(3) });
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request = serde_json::from_str(r#"{"cmd":"audit","limit":5}"#).unwrap();
        assert_eq!(r, Request::Audit { limit: Some(5) });
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request = serde_json::from_str(r#"{"cmd":"runs"}"#).unwrap();
        assert_eq!(r, Request::Runs { limit: None });
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request =
            serde_json::from_str(r#"{"cmd":"table_publish","table_id":4,"confirm":true}"#).unwrap();
        assert_eq!(
            r,
            Request::TablePublish {
                table_id: 4,
                confirm: true
            }
        );
        assert_eq!((r.needs(), r.is_table()), (Role::Operator, true));
        let r: Request = serde_json::from_str(r#"{"cmd":"table_publish","table_id":4}"#).unwrap();
        assert!(matches!(r, Request::TablePublish { confirm: false, .. }));
        let r: Request = serde_json::from_str(r#"{"cmd":"table_generate","run_id":2}"#).unwrap();
        assert_eq!(r.needs(), Role::Operator);
        for text in [r#"{"cmd":"table_status"}"#, r#"{"cmd":"table_list"}"#] {
            let r: Request = serde_json::from_str(text).unwrap();
            assert_eq!((r.needs(), r.is_table()), (Role::Viewer, true), "{text}");
        }
        assert!(!Request::Zero.is_table());
        let r: Request = serde_json::from_str(r#"{"cmd":"nominal","mm":null}"#).unwrap();
        assert_eq!(r, Request::Nominal { mm: None });
        let r: Request =
            serde_json::from_str(r#"{"cmd":"strategy","strategy":"encoder"}"#).unwrap();
        assert_eq!(
            r,
            Request::Strategy {
                strategy: Strategy::Encoder
            }
        );
        // A misspelt field is refused, not ignored (serde checks fields of struct variants).
        let e = serde_json::from_str::<Request>(r#"{"cmd":"follower","action":"jog","mn":1}"#);
        assert!(e.unwrap_err().to_string().contains("unknown field `mn`"));
        assert!(serde_json::from_str::<Request>(r#"{"cmd":"launch"}"#).is_err());
        let r: Request = serde_json::from_str(
            r#"{"cmd":"follower_map_start","from_mm":0,"to_mm":60,"passes":2}"#,
        )
        .unwrap();
        let Request::FollowerMapStart(mapping) = &r else {
            panic!("{r:?}")
        };
        assert_eq!(
            (
                mapping.from_mm,
                mapping.to_mm,
                mapping.passes,
                mapping.frames
            ),
            (Some(0.0), Some(60.0), Some(2), None)
        );
        assert_eq!(r.needs(), Role::Operator);
        let r: Request = serde_json::from_str(r#"{"cmd":"follower_map_start"}"#).unwrap();
        assert_eq!(r, Request::FollowerMapStart(Default::default()));
        let e = serde_json::from_str::<Request>(r#"{"cmd":"follower_map_start","form_mm":0}"#);
        assert!(
            e.unwrap_err()
                .to_string()
                .contains("unknown field `form_mm`")
        );
        let r: Request = serde_json::from_str(r#"{"cmd":"follower_map_status"}"#).unwrap();
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request =
            serde_json::from_str(r#"{"cmd":"follower_certificate","path":"/tmp/c.csv"}"#).unwrap();
        assert_eq!(
            r,
            Request::FollowerCertificate(crate::service::follower::CertificateImport {
                path: Some("/tmp/c.csv".into()),
                ..Default::default()
            })
        );
        // Serialised back flat, as the command line sends it.
        assert_eq!(
            serde_json::to_value(&r).unwrap(),
            serde_json::json!({"cmd": "follower_certificate", "path": "/tmp/c.csv", "keep_current": false})
        );
        assert_eq!(r.needs(), Role::Operator);
    }

    /// One request of each kind with every numeric field given (nested ones too).
    fn numeric_samples() -> Vec<Request> {
        use crate::service::follower_level::LevelRequest;
        use crate::service::follower_map::MappingRequest;
        vec![
            Request::Subscribe { hz: Some(10.0) },
            Request::Follower {
                action: FollowerAction::Jog,
                mm: Some(0.5),
            },
            Request::Nominal { mm: Some(12.0) },
            Request::RunStart {
                plan: crate::run::PlanSpec {
                    reference_mm: Some(0.0),
                    ..Default::default()
                },
                dialect: None,
                notes: None,
            },
            Request::Runs { limit: Some(5) },
            Request::RunResult { run_id: Some(1) },
            Request::Audit { limit: Some(5) },
            Request::HexapodStart {
                plan: None,
                poses: Some(200),
                out: None,
            },
            Request::TableList { limit: Some(5) },
            Request::TableGenerate { run_id: 1 },
            Request::TablePublish {
                table_id: 1,
                confirm: false,
            },
            Request::AlignRead { at_mm: Some(0.0) },
            Request::AlignTarget {
                psd: 2,
                x: 1.0,
                y: -1.0,
            },
            Request::AlignAdvice {
                from_mm: 0.0,
                to_mm: 500.0,
                axis: None,
            },
            Request::FollowerMap { id: Some(1) },
            Request::FollowerMapStart(MappingRequest {
                from_mm: Some(0.0),
                to_mm: Some(400.0),
                step_mm: Some(3.75),
                passes: Some(2),
                frames: Some(1000),
                lead_mm: Some(5.0),
                probe_every: Some(13),
                feed_mm_min: Some(2000.0),
                ..Default::default()
            }),
            Request::FollowerLevelStart(LevelRequest {
                from_mm: Some(0.0),
                to_mm: Some(400.0),
                station_mm: Some(100.0),
                readings: Some(20),
                feed_mm_min: Some(2000.0),
                ..Default::default()
            }),
            Request::FollowerLevelReading {
                arcsec: serde_json::json!(1.5),
            },
        ]
    }

    /// The JSON paths (object keys) of every number in `v`.
    fn number_paths(v: &serde_json::Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        match v {
            serde_json::Value::Number(_) => out.push(path.clone()),
            serde_json::Value::Object(m) => {
                for (k, x) in m {
                    path.push(k.clone());
                    number_paths(x, path, out);
                    path.pop();
                }
            }
            _ => {}
        }
    }

    /// Every numeric field of every request, set in turn to the extremes JSON can carry
    /// (tiny, huge, negative, zero, negative zero, subnormal, the largest integers): the line
    /// is refused by serde (a fraction or a sign an integer field cannot hold), accepted by
    /// `Request::check`, or refused by it naming the field; never a panic.
    #[test]
    fn every_numeric_field_is_range_checked() {
        const EXTREMES: [&str; 11] = [
            "1e-300",
            "1e300",
            "-1",
            "0",
            "-0.0",
            "5e-324",
            "2.2250738585072014e-308",
            "9223372036854775807",
            "-9223372036854775808",
            "18446744073709551615",
            "1.7976931348623157e308",
        ];
        let (mut fields, mut refused) = (0, 0);
        for sample in numeric_samples() {
            assert_eq!(sample.check(), Ok(()), "{sample:?}");
            let v = serde_json::to_value(&sample).unwrap();
            let mut paths = Vec::new();
            number_paths(&v, &mut Vec::new(), &mut paths);
            assert!(!paths.is_empty(), "{v}");
            for path in paths {
                fields += 1;
                let name = path.last().unwrap().clone();
                for x in EXTREMES {
                    let mut w = v.clone();
                    let leaf = path.iter().fold(&mut w, |w, k| &mut w[k.as_str()]);
                    *leaf = serde_json::json!("@X@");
                    let line = w.to_string().replace("\"@X@\"", x);
                    let Ok(r) = serde_json::from_str::<Request>(&line) else {
                        continue;
                    };
                    if let Err(e) = r.check() {
                        refused += 1;
                        assert!(e.contains(&name), "{line}: {e}");
                        assert!(!e.contains("Some("), "{line}: {e}");
                    }
                }
            }
        }
        assert_eq!(fields, 40, "numeric fields covered");
        assert!(refused > 100, "{refused}");
        let r: Request = serde_json::from_str(r#"{"cmd":"subscribe","hz":1e-300}"#).unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            r#""hz": 1e-300 Hz is out of range: use 0.1 to 100 Hz"#
        );
        let r: Request =
            serde_json::from_str(r#"{"cmd":"follower_map_start","frames":5,"passes":2}"#).unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            r#""frames": 5 is out of range: use 10 to 100000"#
        );
        let r: Request = serde_json::from_str(
            r#"{"cmd":"run_start","plan":{"axis":"X","start_mm":0,"end_mm":100,"targets":11,"runs":5,"overrun_mm":2,"dwell_s":1e300,"feed_mm_min":3000,"lead_mm":0}}"#,
        )
        .unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            "test plan: dwell_s: 1e300 s is out of range: use 0 to 3600 s"
        );
        let r: Request = serde_json::from_str(r#"{"cmd":"table_publish","table_id":0}"#).unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            r#""table_id": 0 is not an id: give a stored one's, 1 or more"#
        );
    }

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
