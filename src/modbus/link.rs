//! The client link (DESIGN §10): one task owns the TCP connection; [`Link`] is a cloneable
//! handle that queues calls to it (rodbus' channel design, written anew).
//!
//! Guards added around tokio-modbus, which has none of them:
//! - a per-call timeout;
//! - TCP_NODELAY, so a request is not held back by Nagle's algorithm;
//! - drop-and-reconnect after any transport error, timeout or malformed/mismatched reply. A
//!   timed-out call otherwise leaves its late reply in the socket, to be taken as the answer
//!   to the next request (off by one). A Modbus exception is a well-formed reply matched to its
//!   request: the connection is in step and is kept (reconnecting would not change the
//!   device's answer, and a wrong map would otherwise cause a reconnect storm);
//! - reply checks done here: the register count of a read, the echo of a write (tokio-modbus
//!   only `debug_assert!`s the count, which panics in debug builds on a short reply);
//! - reconnect with exponential backoff ([`Backoff`]), calls failing fast with
//!   [`LinkError::Disconnected`] while the link is down;
//! - the [`LinkState`] on a `tokio::sync::watch` for the console, and [`LinkStats`]. The
//!   state says what the device does, not what the socket does: a TCP connection is
//!   [`LinkState::Connected`] until the first good reply makes it [`LinkState::Up`] (a device
//!   that accepts connections and never answers is never up); a device answering with Modbus
//!   exceptions is [`LinkState::Refusing`], named and logged (once per run of exceptions; the
//!   same exception at most every [`EXCEPTION_LOG_EVERY`]).
//!
//! A call whose caller gave up (its future dropped) is still completed by the task, so the
//! connection stays in step. The task ends when every handle is dropped.

use super::codec::{AddressError, ReadRange, WriteRange};
use super::{Exception, RegisterKind};
use std::borrow::Cow;
use std::collections::VecDeque;
use std::fmt;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use thiserror::Error;
use tokio::net::TcpStream;
use tokio::sync::{mpsc, oneshot, watch};
use tokio_modbus::client::{Client, Context};
use tokio_modbus::prelude::{Request, Response, SlaveContext};
use tokio_modbus::{ProtocolError, Slave};

/// What went wrong with a reply.
#[derive(Clone, Copy, Debug, Error, PartialEq, Eq)]
pub enum ReplyFault {
    #[error("{got} registers instead of the {expected} requested")]
    Count { expected: u16, got: usize },
    #[error("the reply's transaction or unit id does not match the request")]
    Header,
    #[error("the reply's function code does not match the request")]
    Function,
    #[error("the write reply does not echo the request")]
    Echo,
    #[error("malformed reply frame")]
    Malformed,
}

/// Why a call failed. Copyable, so it can sit in [`LinkState`] and be counted.
#[derive(Clone, Copy, Debug, Error, PartialEq, Eq)]
pub enum LinkError {
    #[error("no reply within {}", crate::util::time::span(*.0))]
    Timeout(Duration),
    #[error("not connected (the link is reconnecting)")]
    Disconnected,
    #[error("cannot connect: {0}")]
    Connect(io::ErrorKind),
    #[error("connection lost: {0}")]
    Io(io::ErrorKind),
    #[error("the device answered with {0}")]
    Exception(Exception),
    #[error("invalid reply: {0}")]
    InvalidReply(ReplyFault),
    #[error("invalid request: {0}")]
    Address(AddressError),
    #[error("the link task has stopped")]
    Closed,
}

impl LinkError {
    /// Whether the connection must be dropped after this error (it may be out of step).
    pub fn drops_connection(&self) -> bool {
        matches!(
            self,
            LinkError::Timeout(_) | LinkError::Io(_) | LinkError::InvalidReply(_)
        )
    }
}

/// The first exception of a run of exception replies is logged, unless the same exception
/// was logged less than this ago (a device alternating good replies and exceptions).
pub const EXCEPTION_LOG_EVERY: Duration = Duration::from_secs(10);

/// The link's state, as the console shows it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LinkState {
    /// Connecting (attempt counts from 1 since the last connection).
    Connecting { attempt: u32 },
    /// The TCP connection is open since `since`, but no good reply has come yet.
    Connected { since: Instant },
    /// Good replies since `since`.
    Up { since: Instant },
    /// Connected, but every reply since `since` has been a Modbus exception, the last one
    /// `exception` (the connection is kept: it is in step).
    Refusing {
        exception: Exception,
        since: Instant,
    },
    /// Down after `error`; the next attempt is at `retry_at`.
    Down { error: LinkError, retry_at: Instant },
    /// Every handle was dropped; the task has ended.
    Closed,
}

impl LinkState {
    /// Whether good replies are coming.
    pub fn is_up(&self) -> bool {
        matches!(self, LinkState::Up { .. })
    }

    /// Whether the TCP connection is open (calls go out), whatever the replies.
    pub fn is_connected(&self) -> bool {
        matches!(
            self,
            LinkState::Connected { .. } | LinkState::Up { .. } | LinkState::Refusing { .. }
        )
    }

    /// The short name the snapshot shows: "connecting", "connected", "up", "refusing",
    /// "down" or "closed".
    pub fn name(&self) -> &'static str {
        match self {
            LinkState::Connecting { .. } => "connecting",
            LinkState::Connected { .. } => "connected",
            LinkState::Up { .. } => "up",
            LinkState::Refusing { .. } => "refusing",
            LinkState::Down { .. } => "down",
            LinkState::Closed => "closed",
        }
    }

    /// The exception the device has been answering with, and for how long at `now`.
    pub fn refusing_for(&self, now: Instant) -> Option<(Exception, Duration)> {
        match self {
            LinkState::Refusing { exception, since } => {
                Some((*exception, now.saturating_duration_since(*since)))
            }
            _ => None,
        }
    }
}

impl fmt::Display for LinkState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LinkState::Connecting { attempt } => write!(f, "connecting (attempt {attempt})"),
            LinkState::Connected { since } => write!(
                f,
                "connected for {:.1} s, no reply yet",
                crate::util::clock::since(*since).as_secs_f64()
            ),
            LinkState::Up { since } => write!(
                f,
                "up for {:.1} s",
                crate::util::clock::since(*since).as_secs_f64()
            ),
            LinkState::Refusing { exception, since } => write!(
                f,
                "every reply for {:.1} s is {exception}",
                crate::util::clock::since(*since).as_secs_f64()
            ),
            LinkState::Down { error, retry_at } => write!(
                f,
                "down: {error}; retry in {:.1} s",
                retry_at
                    .saturating_duration_since(crate::util::clock::now())
                    .as_secs_f64()
            ),
            LinkState::Closed => f.write_str("closed"),
        }
    }
}

/// Link settings.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkConfig {
    /// The device (Modbus TCP, usually port 502).
    pub addr: SocketAddr,
    /// Per-call timeout (default 500 ms).
    pub timeout: Duration,
    /// Connect timeout (default 1 s).
    pub connect_timeout: Duration,
    /// First reconnect delay (default 50 ms), doubled after each failure up to `backoff_max`.
    pub backoff_min: Duration,
    /// Longest reconnect delay (default 1 s): the worst added outage after a device returns.
    pub backoff_max: Duration,
    /// Calls that may wait for the task (default 32).
    pub queue: usize,
    /// Calls in the statistics window (default 1024).
    pub window: usize,
}

impl LinkConfig {
    /// Defaults for `addr`.
    pub fn new(addr: SocketAddr) -> Self {
        LinkConfig {
            addr,
            timeout: Duration::from_millis(500),
            connect_timeout: Duration::from_secs(1),
            backoff_min: Duration::from_millis(50),
            backoff_max: Duration::from_secs(1),
            queue: 32,
            window: 1024,
        }
    }
}

pub use crate::util::backoff::Backoff;

/// The span rates are taken over: the last second, as the snapshot documents.
pub const RATE_SPAN: Duration = Duration::from_secs(1);

/// The last `capacity` events with their latency: rate and percentiles over that window
/// (sans-I/O; time is an argument).
#[derive(Clone, Debug)]
pub struct Window {
    capacity: usize,
    events: VecDeque<(Instant, Duration)>,
}

impl Window {
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(2);
        Window {
            capacity,
            events: VecDeque::with_capacity(capacity),
        }
    }
    pub fn push(&mut self, at: Instant, latency: Duration) {
        if self.events.len() == self.capacity {
            self.events.pop_front();
        }
        self.events.push_back((at, latency));
    }
    pub fn len(&self) -> usize {
        self.events.len()
    }
    pub fn is_empty(&self) -> bool {
        self.events.is_empty()
    }
    /// Events per second over the last second before `now` ([`RATE_SPAN`]): the events in
    /// it, per second. When the window holds less than a second of events (fast events, or
    /// the first second), over the span from its oldest event to `now` instead; so it decays
    /// to zero when events stop. `0` with fewer than two events.
    pub fn rate_hz(&self, now: Instant) -> f64 {
        let (Some(first), true) = (self.events.front(), self.events.len() >= 2) else {
            return 0.0;
        };
        match now.checked_sub(RATE_SPAN) {
            Some(from) if first.0 <= from => {
                let older = self.events.partition_point(|e| e.0 <= from);
                (self.events.len() - older) as f64 / RATE_SPAN.as_secs_f64()
            }
            _ => {
                let span = now.saturating_duration_since(first.0).as_secs_f64();
                if span <= 0.0 {
                    return 0.0;
                }
                (self.events.len() - 1) as f64 / span
            }
        }
    }
    /// The `q`-quantile (0..=1) of the latencies, nearest rank; `None` when empty.
    pub fn quantile(&self, q: f64) -> Option<Duration> {
        if self.events.is_empty() {
            return None;
        }
        let mut v: Vec<Duration> = self.events.iter().map(|e| e.1).collect();
        let rank = (q.clamp(0.0, 1.0) * v.len() as f64).ceil() as usize;
        let k = rank.clamp(1, v.len()) - 1;
        let (_, x, _) = v.select_nth_unstable(k);
        Some(*x)
    }
}

/// Link statistics (a snapshot).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkStats {
    /// Calls handled by the task (including those failed while down).
    pub requests: u64,
    /// Calls answered with data.
    pub ok: u64,
    /// Calls that failed, for any reason.
    pub errors: u64,
    /// Of which timeouts and exceptions.
    pub timeouts: u64,
    pub exceptions: u64,
    /// Successful connections after the first.
    pub reconnects: u64,
    /// The last exception the device answered with, and when.
    pub last_exception: Option<(Exception, Instant)>,
    /// Successful calls per second over the last second.
    pub rate_hz: f64,
    /// Latency of successful calls (task dequeue to reply) over the window.
    pub latency_p50: Option<Duration>,
    pub latency_p99: Option<Duration>,
}

pub(super) struct Counters {
    requests: u64,
    ok: u64,
    errors: u64,
    timeouts: u64,
    exceptions: u64,
    reconnects: u64,
    last_exception: Option<(Exception, Instant)>,
    window: Window,
}

impl Counters {
    fn record<T>(&mut self, outcome: &Result<T, LinkError>, started: Instant, now: Instant) {
        self.requests += 1;
        match outcome {
            Ok(_) => {
                self.ok += 1;
                self.window
                    .push(now, now.saturating_duration_since(started));
            }
            Err(e) => {
                self.errors += 1;
                match e {
                    LinkError::Timeout(_) => self.timeouts += 1,
                    LinkError::Exception(x) => {
                        self.exceptions += 1;
                        self.last_exception = Some((*x, now));
                    }
                    _ => {}
                }
            }
        }
    }
}

#[derive(Debug)]
enum Op {
    Read(RegisterKind, ReadRange),
    WriteSingle(u16, u16),
    WriteMultiple(WriteRange, Vec<u16>),
}

enum Reply {
    Registers(Vec<u16>),
    Written,
}

struct Call {
    unit: u8,
    op: Op,
    reply: oneshot::Sender<Result<Reply, LinkError>>,
}

/// The read side of a link: its address, state and statistics (for the snapshot and the
/// console). Shared by the [`Link`] task and the acquisition's [`PacedReader`](super::PacedReader).
#[derive(Clone)]
pub struct Monitor {
    state: watch::Receiver<LinkState>,
    counters: Arc<Mutex<Counters>>,
    addr: SocketAddr,
}

impl fmt::Debug for Monitor {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Link")
            .field("addr", &self.addr)
            .field("state", &*self.state.borrow())
            .finish()
    }
}

/// The writer's side of a [`Monitor`]: counts every outcome and moves the state between
/// connected, up and refusing by the replies.
pub(super) struct Reporter {
    pub(super) state: watch::Sender<LinkState>,
    pub(super) counters: Arc<Mutex<Counters>>,
    addr: SocketAddr,
    /// Exceptions in the current run of exception replies.
    run: u64,
    /// The exception last logged, and when.
    last_log: Option<(Exception, Instant)>,
}

impl Reporter {
    pub(super) fn new(addr: SocketAddr, window: usize) -> (Reporter, Monitor) {
        let (state, rx) = watch::channel(LinkState::Connecting { attempt: 1 });
        let counters = Arc::new(Mutex::new(Counters {
            requests: 0,
            ok: 0,
            errors: 0,
            timeouts: 0,
            exceptions: 0,
            reconnects: 0,
            last_exception: None,
            window: Window::new(window),
        }));
        let monitor = Monitor {
            state: rx,
            counters: counters.clone(),
            addr,
        };
        (
            Reporter {
                state,
                counters,
                addr,
                run: 0,
                last_log: None,
            },
            monitor,
        )
    }

    /// The outcome of a call that went out on the connection: counted, and the state follows
    /// the reply (a transport error is reported by the caller with [`down`](Self::down)).
    pub(super) fn record<T>(
        &mut self,
        outcome: &Result<T, LinkError>,
        started: Instant,
        now: Instant,
    ) {
        lock(&self.counters).record(outcome, started, now);
        match outcome {
            Ok(_) => {
                let run = std::mem::take(&mut self.run);
                let up = self.state.send_if_modified(|s| {
                    let change = !s.is_up();
                    if change {
                        *s = LinkState::Up { since: now };
                    }
                    change
                });
                if up && run > 0 {
                    tracing::info!(addr = %self.addr, exceptions = run, "modbus device answers again");
                } else if up {
                    tracing::info!(addr = %self.addr, "modbus link up: the device answers");
                }
            }
            Err(LinkError::Exception(x)) => {
                self.run += 1;
                let x = *x;
                let changed = self.state.send_if_modified(|s| match s {
                    LinkState::Refusing { exception, .. } if *exception == x => false,
                    LinkState::Refusing { exception, .. } => {
                        *exception = x;
                        true
                    }
                    _ => {
                        *s = LinkState::Refusing {
                            exception: x,
                            since: now,
                        };
                        true
                    }
                });
                let quiet = self.last_log.is_some_and(|(last, t)| {
                    last == x && now.saturating_duration_since(t) < EXCEPTION_LOG_EVERY
                });
                if changed && !quiet {
                    self.last_log = Some((x, now));
                    tracing::warn!(addr = %self.addr, "modbus device answered with {x}");
                }
            }
            Err(_) => {}
        }
    }

    /// The TCP connection is open: connected, not up until a good reply.
    pub(super) fn connected(&mut self, now: Instant, reconnect: bool) {
        if reconnect {
            lock(&self.counters).reconnects += 1;
        }
        self.run = 0;
        self.state.send_replace(LinkState::Connected { since: now });
        tracing::info!(addr = %self.addr, "modbus connection open, awaiting the first reply");
    }

    /// The connection failed or was dropped after `error`; the next attempt is at `retry_at`.
    pub(super) fn down(&mut self, error: LinkError, retry_at: Instant) {
        self.run = 0;
        tracing::warn!(addr = %self.addr, %error, "modbus link down");
        self.state.send_replace(LinkState::Down { error, retry_at });
    }
}

impl Monitor {
    /// The device address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The link state, to watch.
    pub fn state(&self) -> watch::Receiver<LinkState> {
        self.state.clone()
    }

    /// Wait until the link is connected (calls go out), at most `timeout`; whether it is.
    pub async fn wait_connected(&self, timeout: Duration) -> bool {
        let mut rx = self.state.clone();
        matches!(
            tokio::time::timeout(
                timeout,
                rx.wait_for(|s| s.is_connected() || *s == LinkState::Closed)
            )
            .await,
            Ok(Ok(s)) if s.is_connected()
        )
    }

    /// A statistics snapshot.
    pub fn stats(&self) -> LinkStats {
        let c = lock(&self.counters);
        let now = crate::util::clock::now();
        LinkStats {
            requests: c.requests,
            ok: c.ok,
            errors: c.errors,
            timeouts: c.timeouts,
            exceptions: c.exceptions,
            reconnects: c.reconnects,
            last_exception: c.last_exception,
            rate_hz: c.window.rate_hz(now),
            latency_p50: c.window.quantile(0.5),
            latency_p99: c.window.quantile(0.99),
        }
    }
}

/// A handle to the link task. Cheap to clone; the task ends when the last handle is dropped.
#[derive(Clone)]
pub struct Link {
    tx: mpsc::Sender<Call>,
    monitor: Monitor,
}

impl fmt::Debug for Link {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.monitor.fmt(f)
    }
}

impl Link {
    /// Start the link task on the current Tokio runtime (panics outside one, like
    /// `tokio::spawn`). It connects at once and keeps reconnecting until every handle is gone.
    pub fn spawn(config: LinkConfig) -> Link {
        let (tx, rx) = mpsc::channel(config.queue.max(1));
        let (reporter, monitor) = Reporter::new(config.addr, config.window);
        tokio::spawn(run(config, rx, reporter));
        Link { tx, monitor }
    }

    /// The read side: address, state and statistics.
    pub fn monitor(&self) -> Monitor {
        self.monitor.clone()
    }

    /// The device address.
    pub fn addr(&self) -> SocketAddr {
        self.monitor.addr()
    }

    /// The link state, to watch.
    pub fn state(&self) -> watch::Receiver<LinkState> {
        self.monitor.state()
    }

    /// Wait until the link is connected (calls go out), at most `timeout`; whether it is.
    pub async fn wait_connected(&self, timeout: Duration) -> bool {
        self.monitor.wait_connected(timeout).await
    }

    /// A statistics snapshot.
    pub fn stats(&self) -> LinkStats {
        self.monitor.stats()
    }

    async fn call(&self, unit: u8, op: Op) -> Result<Reply, LinkError> {
        let (reply, rx) = oneshot::channel();
        self.tx
            .send(Call { unit, op, reply })
            .await
            .map_err(|_| LinkError::Closed)?;
        rx.await.map_err(|_| LinkError::Closed)?
    }

    /// Read registers of `kind` (function 4 for input, 3 for holding).
    pub async fn read(
        &self,
        kind: RegisterKind,
        unit: u8,
        range: ReadRange,
    ) -> Result<Vec<u16>, LinkError> {
        match self.call(unit, Op::Read(kind, range)).await? {
            Reply::Registers(v) => Ok(v),
            Reply::Written => Err(LinkError::InvalidReply(ReplyFault::Function)),
        }
    }

    /// Read input registers (function 4).
    pub async fn read_input_registers(
        &self,
        unit: u8,
        range: ReadRange,
    ) -> Result<Vec<u16>, LinkError> {
        self.read(RegisterKind::Input, unit, range).await
    }

    /// Read holding registers (function 3).
    pub async fn read_holding_registers(
        &self,
        unit: u8,
        range: ReadRange,
    ) -> Result<Vec<u16>, LinkError> {
        self.read(RegisterKind::Holding, unit, range).await
    }

    /// Write one holding register (function 6).
    pub async fn write_single_register(
        &self,
        unit: u8,
        addr: u16,
        value: u16,
    ) -> Result<(), LinkError> {
        self.call(unit, Op::WriteSingle(addr, value))
            .await
            .map(|_| ())
    }

    /// Write 1..=123 holding registers from `start` (function 16).
    pub async fn write_multiple_registers(
        &self,
        unit: u8,
        start: u16,
        values: &[u16],
    ) -> Result<(), LinkError> {
        let range = WriteRange::for_values(start, values).map_err(LinkError::Address)?;
        self.call(unit, Op::WriteMultiple(range, values.to_vec()))
            .await
            .map(|_| ())
    }
}

fn lock(c: &Mutex<Counters>) -> std::sync::MutexGuard<'_, Counters> {
    // Counters stay consistent even if a holder panicked: keep going.
    c.lock().unwrap_or_else(|p| p.into_inner())
}

/// A TCP connection to the device in `cfg` within its connect timeout, with TCP_NODELAY.
pub(super) async fn open_tcp(cfg: &LinkConfig) -> Result<TcpStream, LinkError> {
    let stream = match tokio::time::timeout(cfg.connect_timeout, TcpStream::connect(cfg.addr)).await
    {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return Err(LinkError::Connect(e.kind())),
        Err(_) => return Err(LinkError::Connect(io::ErrorKind::TimedOut)),
    };
    stream
        .set_nodelay(true)
        .map_err(|e| LinkError::Connect(e.kind()))?;
    Ok(stream)
}

async fn connect(cfg: &LinkConfig) -> Result<Context, LinkError> {
    let stream = open_tcp(cfg).await?;
    Ok(tokio_modbus::client::tcp::attach_slave(stream, Slave(0)))
}

/// The reconnect side of a reader that owns its connection (the paced and the pipelined
/// readers): the backoff between attempts, the state reports, the statistics. Reports
/// [`LinkState::Closed`] when dropped.
pub(super) struct Redial {
    backoff: Backoff,
    retry_at: Option<Instant>,
    attempt: u32,
    connected_before: bool,
    pub(super) report: Reporter,
}

impl Drop for Redial {
    fn drop(&mut self) {
        self.report.state.send_replace(LinkState::Closed);
    }
}

impl Redial {
    pub(super) fn new(cfg: &LinkConfig) -> (Redial, Monitor) {
        let (report, monitor) = Reporter::new(cfg.addr, cfg.window);
        let redial = Redial {
            backoff: Backoff::new(cfg.backoff_min, cfg.backoff_max),
            retry_at: None,
            attempt: 0,
            connected_before: false,
            report,
        };
        (redial, monitor)
    }

    /// Wait for the next attempt (the backoff), then connect ([`open_tcp`]); the state says
    /// connecting, then connected (or down, with the next attempt, on failure).
    pub(super) async fn dial(&mut self, cfg: &LinkConfig) -> Result<TcpStream, LinkError> {
        if let Some(at) = self.retry_at {
            tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await;
        }
        self.attempt += 1;
        self.report.state.send_replace(LinkState::Connecting {
            attempt: self.attempt,
        });
        match open_tcp(cfg).await {
            Ok(stream) => {
                self.report
                    .connected(crate::util::clock::now(), self.connected_before);
                self.connected_before = true;
                self.attempt = 0;
                self.retry_at = None;
                Ok(stream)
            }
            Err(e) => Err(self.down(e)),
        }
    }

    /// The connection is gone after `error`: schedule the next attempt and report it.
    pub(super) fn down(&mut self, error: LinkError) -> LinkError {
        let retry_at = crate::util::clock::now() + self.backoff.next_delay();
        self.retry_at = Some(retry_at);
        self.report.down(error, retry_at);
        error
    }

    /// Count an outcome (started at `started`, ended at `now`); a good reply resets the
    /// backoff.
    pub(super) fn record<T>(
        &mut self,
        outcome: &Result<T, LinkError>,
        started: Instant,
        now: Instant,
    ) {
        if outcome.is_ok() {
            self.backoff.reset();
        }
        self.report.record(outcome, started, now);
    }
}

enum Served {
    /// Every handle is gone.
    Closed,
    /// The connection failed and was dropped.
    Failed(LinkError),
}

/// The task: connect, serve calls until an error drops the connection, back off, repeat.
async fn run(cfg: LinkConfig, mut rx: mpsc::Receiver<Call>, mut reporter: Reporter) {
    let mut backoff = Backoff::new(cfg.backoff_min, cfg.backoff_max);
    let mut attempt = 0u32;
    let mut connected_before = false;
    loop {
        attempt += 1;
        reporter
            .state
            .send_replace(LinkState::Connecting { attempt });
        let error = match connect(&cfg).await {
            Ok(ctx) => {
                attempt = 0;
                reporter.connected(crate::util::clock::now(), connected_before);
                connected_before = true;
                match serve(&cfg, ctx, &mut rx, &mut reporter, &mut backoff).await {
                    Served::Closed => break,
                    Served::Failed(e) => e,
                }
            }
            Err(e) => e,
        };
        let retry_at = crate::util::clock::now() + backoff.next_delay();
        reporter.down(error, retry_at);
        // Fail calls fast while down, so callers see the outage instead of queueing into it.
        let deadline = tokio::time::Instant::from_std(retry_at);
        loop {
            tokio::select! {
                _ = tokio::time::sleep_until(deadline) => break,
                call = rx.recv() => match call {
                    None => {
                        reporter.state.send_replace(LinkState::Closed);
                        return;
                    }
                    Some(call) => {
                        let now = crate::util::clock::now();
                        let outcome: Result<Reply, LinkError> = Err(LinkError::Disconnected);
                        lock(&reporter.counters).record(&outcome, now, now);
                        let _ = call.reply.send(outcome);
                    }
                },
            }
        }
    }
    reporter.state.send_replace(LinkState::Closed);
}

async fn serve(
    cfg: &LinkConfig,
    mut ctx: Context,
    rx: &mut mpsc::Receiver<Call>,
    reporter: &mut Reporter,
    backoff: &mut Backoff,
) -> Served {
    loop {
        let Some(call) = rx.recv().await else {
            let _ = ctx.disconnect().await;
            return Served::Closed;
        };
        let started = crate::util::clock::now();
        ctx.set_slave(Slave(call.unit));
        let outcome = match tokio::time::timeout(cfg.timeout, ctx.call(request(&call.op))).await {
            Err(_) => Err(LinkError::Timeout(cfg.timeout)),
            Ok(r) => check(&call.op, r),
        };
        reporter.record(&outcome, started, crate::util::clock::now());
        let fatal = match &outcome {
            Ok(_) => {
                backoff.reset();
                None
            }
            Err(e) if e.drops_connection() => Some(*e),
            Err(_) => None,
        };
        let _ = call.reply.send(outcome);
        if let Some(e) = fatal {
            // Dropping the context closes the socket: a late reply can no longer be misread.
            drop(ctx);
            return Served::Failed(e);
        }
    }
}

fn request(op: &Op) -> Request<'static> {
    match op {
        Op::Read(RegisterKind::Input, r) => Request::ReadInputRegisters(r.start(), r.count()),
        Op::Read(RegisterKind::Holding, r) => Request::ReadHoldingRegisters(r.start(), r.count()),
        Op::WriteSingle(a, v) => Request::WriteSingleRegister(*a, *v),
        Op::WriteMultiple(r, v) => {
            Request::WriteMultipleRegisters(r.start(), Cow::Owned(v.clone()))
        }
    }
}

fn transport(e: tokio_modbus::Error) -> LinkError {
    match e {
        tokio_modbus::Error::Protocol(ProtocolError::HeaderMismatch { .. }) => {
            LinkError::InvalidReply(ReplyFault::Header)
        }
        tokio_modbus::Error::Protocol(ProtocolError::FunctionCodeMismatch { .. }) => {
            LinkError::InvalidReply(ReplyFault::Function)
        }
        tokio_modbus::Error::Transport(e) if e.kind() == io::ErrorKind::InvalidData => {
            LinkError::InvalidReply(ReplyFault::Malformed)
        }
        tokio_modbus::Error::Transport(e) => LinkError::Io(e.kind()),
    }
}

/// The reply checked against its request (sans-I/O).
fn check(
    op: &Op,
    r: Result<Result<Response, tokio_modbus::ExceptionCode>, tokio_modbus::Error>,
) -> Result<Reply, LinkError> {
    let response = r
        .map_err(transport)?
        .map_err(|e| LinkError::Exception(e.into()))?;
    match (op, response) {
        (Op::Read(RegisterKind::Input, r), Response::ReadInputRegisters(v))
        | (Op::Read(RegisterKind::Holding, r), Response::ReadHoldingRegisters(v)) => {
            if v.len() == r.count() as usize {
                Ok(Reply::Registers(v))
            } else {
                Err(LinkError::InvalidReply(ReplyFault::Count {
                    expected: r.count(),
                    got: v.len(),
                }))
            }
        }
        (Op::WriteSingle(a, v), Response::WriteSingleRegister(ra, rv)) => {
            if (*a, *v) == (ra, rv) {
                Ok(Reply::Written)
            } else {
                Err(LinkError::InvalidReply(ReplyFault::Echo))
            }
        }
        (Op::WriteMultiple(r, _), Response::WriteMultipleRegisters(ra, rq)) => {
            if (r.start(), r.count()) == (ra, rq) {
                Ok(Reply::Written)
            } else {
                Err(LinkError::InvalidReply(ReplyFault::Echo))
            }
        }
        _ => Err(LinkError::InvalidReply(ReplyFault::Function)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_rate_and_quantiles() {
        let t0 = crate::util::clock::now();
        let mut w = Window::new(100);
        assert_eq!(w.quantile(0.5), None);
        assert_eq!(w.rate_hz(t0), 0.0);
        // 100 events 10 ms apart, latencies 1..=100 µs.
        for k in 0..100u64 {
            w.push(
                t0 + Duration::from_millis(10 * k),
                Duration::from_micros(k + 1),
            );
        }
        let now = t0 + Duration::from_millis(990);
        assert!((w.rate_hz(now) - 100.0).abs() < 1e-9);
        assert_eq!(w.quantile(0.5), Some(Duration::from_micros(50)));
        assert_eq!(w.quantile(0.99), Some(Duration::from_micros(99)));
        assert_eq!(w.quantile(1.0), Some(Duration::from_micros(100)));
        assert_eq!(w.quantile(0.0), Some(Duration::from_micros(1)));
        // The window keeps the newest events only; the rate decays once events stop.
        w.push(t0 + Duration::from_secs(1), Duration::from_micros(1000));
        assert_eq!(w.len(), 100);
        assert_eq!(w.quantile(1.0), Some(Duration::from_micros(1000)));
        assert!(w.rate_hz(t0 + Duration::from_secs(20)) < 6.0);
    }

    #[test]
    fn the_rate_is_over_the_last_second() {
        // 2 s at 500 Hz, then 1 s at 250 Hz, in a window of 1024 events (about 2 s at
        // 500 Hz): the rate is the last second's 250/s, not a mean over the window.
        let t0 = crate::util::clock::now();
        let mut w = Window::new(1024);
        let mut t = t0;
        for _ in 0..1000 {
            t += Duration::from_millis(2);
            w.push(t, Duration::ZERO);
        }
        assert!((w.rate_hz(t) - 500.0).abs() <= 1.0, "{}", w.rate_hz(t));
        for _ in 0..250 {
            t += Duration::from_millis(4);
            w.push(t, Duration::ZERO);
        }
        assert!((w.rate_hz(t) - 250.0).abs() <= 1.0, "{}", w.rate_hz(t));
        // Half a second without events: 125 events in the last second.
        let later = t + Duration::from_millis(500);
        assert!(
            (w.rate_hz(later) - 125.0).abs() <= 1.0,
            "{}",
            w.rate_hz(later)
        );
        assert_eq!(w.rate_hz(t + Duration::from_secs(2)), 0.0);
    }

    #[test]
    fn the_state_follows_the_replies() {
        let addr: SocketAddr = "127.0.0.1:502".parse().unwrap();
        let (mut r, m) = Reporter::new(addr, 16);
        let rx = m.state();
        let t0 = crate::util::clock::now();
        r.connected(t0, false);
        // A connection is not a reply: connected, not up.
        assert_eq!(*rx.borrow(), LinkState::Connected { since: t0 });
        assert!(!rx.borrow().is_up() && rx.borrow().is_connected());
        let t1 = t0 + Duration::from_millis(5);
        r.record::<()>(&Ok(()), t0, t1);
        assert_eq!(*rx.borrow(), LinkState::Up { since: t1 });
        // Exceptions: refusing since the first, named by the last.
        let x = |c| Err::<(), _>(LinkError::Exception(Exception::from_code(c)));
        let t2 = t1 + Duration::from_millis(5);
        r.record(&x(2), t2, t2);
        r.record(&x(2), t2, t2 + Duration::from_millis(500));
        assert_eq!(
            rx.borrow().refusing_for(t2 + Duration::from_secs(1)),
            Some((Exception::IllegalDataAddress, Duration::from_secs(1)))
        );
        r.record(&x(4), t2, t2 + Duration::from_millis(600));
        assert_eq!(
            *rx.borrow(),
            LinkState::Refusing {
                exception: Exception::ServerDeviceFailure,
                since: t2
            }
        );
        assert_eq!(rx.borrow().name(), "refusing");
        let st = m.stats();
        assert_eq!((st.exceptions, st.errors, st.ok), (3, 3, 1));
        assert_eq!(
            st.last_exception,
            Some((
                Exception::ServerDeviceFailure,
                t2 + Duration::from_millis(600)
            ))
        );
        let t3 = t2 + Duration::from_secs(1);
        r.record::<()>(&Ok(()), t3, t3);
        assert_eq!(*rx.borrow(), LinkState::Up { since: t3 });
        r.down(LinkError::Timeout(Duration::from_millis(200)), t3);
        assert_eq!(rx.borrow().name(), "down");
        r.connected(t3, true);
        assert_eq!(m.stats().reconnects, 1);
        assert_eq!(rx.borrow().name(), "connected");
    }

    fn range(start: u16, count: u16) -> ReadRange {
        ReadRange::new(start, count).unwrap()
    }

    #[test]
    fn replies_are_checked_against_their_request() {
        let op = Op::Read(RegisterKind::Input, range(0, 3));
        assert!(matches!(
            check(&op, Ok(Ok(Response::ReadInputRegisters(vec![1, 2, 3])))),
            Ok(Reply::Registers(v)) if v == [1, 2, 3]
        ));
        assert!(matches!(
            check(&op, Ok(Ok(Response::ReadInputRegisters(vec![1, 2])))),
            Err(LinkError::InvalidReply(ReplyFault::Count {
                expected: 3,
                got: 2
            }))
        ));
        assert!(matches!(
            check(&op, Ok(Ok(Response::ReadHoldingRegisters(vec![1, 2, 3])))),
            Err(LinkError::InvalidReply(ReplyFault::Function))
        ));
        assert!(matches!(
            check(
                &op,
                Ok(Err(tokio_modbus::ExceptionCode::IllegalDataAddress))
            ),
            Err(LinkError::Exception(Exception::IllegalDataAddress))
        ));
        let w = Op::WriteSingle(7, 42);
        assert!(check(&w, Ok(Ok(Response::WriteSingleRegister(7, 42)))).is_ok());
        assert!(matches!(
            check(&w, Ok(Ok(Response::WriteSingleRegister(7, 43)))),
            Err(LinkError::InvalidReply(ReplyFault::Echo))
        ));
        let wm = Op::WriteMultiple(WriteRange::new(10, 2).unwrap(), vec![1, 2]);
        assert!(check(&wm, Ok(Ok(Response::WriteMultipleRegisters(10, 2)))).is_ok());
        assert!(check(&wm, Ok(Ok(Response::WriteMultipleRegisters(10, 1)))).is_err());
        let io = tokio_modbus::Error::Transport(io::Error::from(io::ErrorKind::BrokenPipe));
        assert_eq!(
            check(&op, Err(io)).err(),
            Some(LinkError::Io(io::ErrorKind::BrokenPipe))
        );
    }

    #[test]
    fn which_errors_drop_the_connection() {
        assert!(LinkError::Timeout(Duration::from_millis(1)).drops_connection());
        assert!(LinkError::Io(io::ErrorKind::BrokenPipe).drops_connection());
        assert!(LinkError::InvalidReply(ReplyFault::Header).drops_connection());
        assert!(!LinkError::Exception(Exception::IllegalDataAddress).drops_connection());
        assert!(!LinkError::Disconnected.drops_connection());
    }
}
