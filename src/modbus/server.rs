//! Server scaffolding for our own Modbus TCP servers (the twin's I/O module now; a PLC twin and
//! the pull server later), over tokio-modbus' TCP server.
//!
//! - A [`RegisterBank`] holds the data; [`MemoryBank`] is a plain one.
//! - Requests are validated here, never trusting the library: read quantities 1..=125, write
//!   quantities 1..=123, ranges inside the address space ([`handle`], sans-I/O). Out-of-range
//!   addresses, bad quantities and unsupported functions get the proper Modbus exception
//!   (illegal data address / value / function); the connection is kept.
//! - Peer allow-list: a peer whose IP is not listed has its connection closed on accept, before
//!   any Modbus traffic. It learns nothing about the server's registers, and a closed
//!   connection is what devices with an "accessible IP" list do; answering exceptions instead
//!   would keep unknown peers connected and spending our time. Refusals are counted and logged.
//! - Fault injection for tests: stop listening (closing every connection) and start again on
//!   the same address, delay replies, answer every request with an exception; and a bank may
//!   go silent ([`RegisterBank::responsive`]): the request it was handling, and every later
//!   one, gets no reply, as from a device that died mid-request (the twin's PLC uses it to
//!   drop out after N writes, then stops and restarts the server).
//!
//! - Idle connections: with [`ServerConfig::idle_timeout`] set, a connection on which no complete
//!   request arrived for that long is closed (logged), so idle peers and slow writers that
//!   trickle a frame byte by byte cannot hold a place of `max_connections` for ever.
//!
//! Limits that come from tokio-modbus and that we cannot answer with an exception: a frame its
//! decoder rejects (bad MBAP header, function codes ≥ 0x80, a write whose byte count does not
//! match its quantity) closes that connection; the server keeps running.

use super::codec::{ReadRange, WriteRange};
use super::{Exception, RegisterKind};
use futures_util::future::{self, Either};
use std::future::Future;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use thiserror::Error;
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::task::JoinHandle;
use tokio_modbus::prelude::{Request, Response, SlaveRequest};
use tokio_modbus::server::tcp::Server;

/// Where registers come from. Implementations decide per unit id and, for writes, per peer.
pub trait RegisterBank: Send + Sync + 'static {
    /// Registers `range` of `kind` for `unit` (the range is already validated).
    fn read(&self, unit: u8, kind: RegisterKind, range: ReadRange) -> Result<Vec<u16>, Exception>;

    /// Write holding registers from `range.start()`; read-only by default.
    fn write(
        &self,
        _unit: u8,
        _range: WriteRange,
        _values: &[u16],
        _peer: SocketAddr,
    ) -> Result<(), Exception> {
        Err(Exception::IllegalFunction)
    }

    /// Whether the device answers at all (checked after each request is handled); `false`
    /// leaves that request and later ones unanswered. Always `true` by default.
    fn responsive(&self) -> bool {
        true
    }
}

/// Registers in memory: an input and a holding table, each from address 0, with holding
/// registers writable inside one optional range. Answers every unit id.
#[derive(Debug, Default)]
pub struct MemoryBank {
    tables: Mutex<(Vec<u16>, Vec<u16>)>,
    writable: Option<(u16, u32)>,
}

impl MemoryBank {
    /// `input` and `holding` registers from address 0; holding registers `writable`
    /// (start, count) may be written.
    pub fn new(input: Vec<u16>, holding: Vec<u16>, writable: Option<(u16, u16)>) -> Self {
        MemoryBank {
            tables: Mutex::new((input, holding)),
            writable: writable.map(|(s, c)| (s, s as u32 + c as u32)),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Vec<u16>, Vec<u16>)> {
        self.tables.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Set input registers from `start` (for tests driving the data).
    pub fn set_input(&self, start: u16, values: &[u16]) {
        let mut t = self.lock();
        set(&mut t.0, start, values);
    }

    /// Set holding registers from `start`, bypassing the write rules.
    pub fn set_holding(&self, start: u16, values: &[u16]) {
        let mut t = self.lock();
        set(&mut t.1, start, values);
    }

    /// A copy of the holding registers.
    pub fn holding(&self) -> Vec<u16> {
        self.lock().1.clone()
    }
}

fn set(table: &mut Vec<u16>, start: u16, values: &[u16]) {
    let end = start as usize + values.len();
    if table.len() < end {
        table.resize(end, 0);
    }
    table[start as usize..end].copy_from_slice(values);
}

impl RegisterBank for MemoryBank {
    fn read(&self, _unit: u8, kind: RegisterKind, r: ReadRange) -> Result<Vec<u16>, Exception> {
        let t = self.lock();
        let table = match kind {
            RegisterKind::Input => &t.0,
            RegisterKind::Holding => &t.1,
        };
        table
            .get(r.start() as usize..r.end() as usize)
            .map(<[u16]>::to_vec)
            .ok_or(Exception::IllegalDataAddress)
    }

    fn write(
        &self,
        _unit: u8,
        r: WriteRange,
        values: &[u16],
        _peer: SocketAddr,
    ) -> Result<(), Exception> {
        match self.writable {
            Some((s, e)) if r.start() >= s && r.end() <= e => {}
            _ => return Err(Exception::IllegalDataAddress),
        }
        let mut t = self.lock();
        let slot =
            t.1.get_mut(r.start() as usize..r.end() as usize)
                .ok_or(Exception::IllegalDataAddress)?;
        slot.copy_from_slice(values);
        Ok(())
    }
}

/// Answer one request from `bank` (sans-I/O): validation, dispatch, exceptions.
pub fn handle(
    bank: &dyn RegisterBank,
    unit: u8,
    request: &Request<'_>,
    peer: SocketAddr,
) -> Result<Response, Exception> {
    match request {
        Request::ReadInputRegisters(start, count) => {
            let r = read_range(*start, *count)?;
            let v = bank.read(unit, RegisterKind::Input, r)?;
            checked_len(v, r.count()).map(Response::ReadInputRegisters)
        }
        Request::ReadHoldingRegisters(start, count) => {
            let r = read_range(*start, *count)?;
            let v = bank.read(unit, RegisterKind::Holding, r)?;
            checked_len(v, r.count()).map(Response::ReadHoldingRegisters)
        }
        Request::WriteSingleRegister(addr, value) => {
            let r = WriteRange::new(*addr, 1).map_err(|_| Exception::IllegalDataAddress)?;
            bank.write(unit, r, &[*value], peer)?;
            Ok(Response::WriteSingleRegister(*addr, *value))
        }
        Request::WriteMultipleRegisters(start, values) => {
            let count = u16::try_from(values.len()).map_err(|_| Exception::IllegalDataValue)?;
            if count == 0 || count > super::codec::MAX_WRITE {
                return Err(Exception::IllegalDataValue);
            }
            let r = WriteRange::new(*start, count).map_err(|_| Exception::IllegalDataAddress)?;
            bank.write(unit, r, values, peer)?;
            Ok(Response::WriteMultipleRegisters(*start, count))
        }
        _ => Err(Exception::IllegalFunction),
    }
}

/// Quantity outside 1..=125 is an illegal data value; a range past 65535 an illegal address
/// (Modbus Application Protocol v1.1b3, §6.3/§6.4 state diagrams).
fn read_range(start: u16, count: u16) -> Result<ReadRange, Exception> {
    if count == 0 || count > super::codec::MAX_READ {
        return Err(Exception::IllegalDataValue);
    }
    ReadRange::new(start, count).map_err(|_| Exception::IllegalDataAddress)
}

fn checked_len(v: Vec<u16>, count: u16) -> Result<Vec<u16>, Exception> {
    if v.len() == count as usize {
        Ok(v)
    } else {
        // A bank bug must not put a wrong-length reply on the wire.
        Err(Exception::ServerDeviceFailure)
    }
}

/// Connections a server keeps open at once unless told otherwise.
pub const DEFAULT_MAX_CONNECTIONS: usize = 32;

/// A refused connection is logged at most this often (with the count refused meanwhile).
const REFUSAL_LOG_EVERY: Duration = Duration::from_secs(10);

/// Server settings.
#[derive(Clone, Debug, PartialEq)]
pub struct ServerConfig {
    /// Where to listen (port 0: an ephemeral port, kept across stop/start).
    pub bind: SocketAddr,
    /// Peers allowed to connect; `None` allows everyone.
    pub allow: Option<Vec<IpAddr>>,
    /// Connections open at once; more are closed on accept and logged (default
    /// [`DEFAULT_MAX_CONNECTIONS`]). Each connection's buffers are bounded by the Modbus
    /// frame (at most 260 bytes per ADU).
    pub max_connections: usize,
    /// Close a connection on which no complete request arrived for this long (`None`: keep
    /// it for as long as the peer does).
    pub idle_timeout: Option<Duration>,
}

impl ServerConfig {
    pub fn new(bind: SocketAddr) -> Self {
        ServerConfig {
            bind,
            allow: None,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout: None,
        }
    }
}

/// Why the server could not start.
#[derive(Debug, Error)]
pub enum ServerError {
    #[error("cannot listen on {addr}: {source}")]
    Bind { addr: SocketAddr, source: io::Error },
}

/// Server counters (a snapshot).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServerStats {
    pub accepted: u64,
    pub refused: u64,
    pub requests: u64,
    pub exceptions: u64,
    /// Connections being served now.
    pub open: u64,
}

#[derive(Clone, Copy, Debug, Default)]
struct Faults {
    delay: Duration,
    exception: Option<Exception>,
}

/// What the accept loop and the connections share.
struct Inner {
    addr: SocketAddr,
    allow: Option<Vec<IpAddr>>,
    bank: Arc<dyn RegisterBank>,
    faults: Mutex<Faults>,
    accepted: AtomicU64,
    refused: AtomicU64,
    requests: AtomicU64,
    exceptions: AtomicU64,
    /// Connections whose service still exists.
    open: AtomicU64,
    max_connections: usize,
    idle_timeout: Option<Duration>,
    /// When a refusal was last logged, and the refusals since.
    refusal_log: Mutex<(Option<Instant>, u64)>,
}

impl Inner {
    /// Count a refusal of `peer` and log it, at most every [`REFUSAL_LOG_EVERY`].
    fn refuse(&self, peer: SocketAddr, why: &str) {
        self.refused.fetch_add(1, Ordering::Relaxed);
        let now = crate::util::clock::now();
        let mut log = self.refusal_log.lock().unwrap_or_else(|p| p.into_inner());
        log.1 += 1;
        if log
            .0
            .is_none_or(|t| now.saturating_duration_since(t) >= REFUSAL_LOG_EVERY)
        {
            tracing::warn!(server = %self.addr, %peer, refused = log.1, "modbus connection refused: {why}");
            *log = (Some(now), 0);
        }
    }
}

/// The accept loop's task, held by the handles only: the last handle dropped aborts it, which
/// closes every connection.
struct Control {
    task: Mutex<Option<JoinHandle<()>>>,
}

impl Drop for Control {
    fn drop(&mut self) {
        if let Some(t) = self.task.get_mut().ok().and_then(Option::take) {
            t.abort();
        }
    }
}

/// A running server. Cloneable; the server stops when the last handle is dropped.
#[derive(Clone)]
pub struct ServerHandle {
    inner: Arc<Inner>,
    control: Arc<Control>,
}

impl std::fmt::Debug for ServerHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServerHandle")
            .field("addr", &self.inner.addr)
            .finish()
    }
}

fn listen(addr: SocketAddr) -> Result<TcpListener, ServerError> {
    let err = |source| ServerError::Bind { addr, source };
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()
    } else {
        TcpSocket::new_v6()
    }
    .map_err(err)?;
    // Rebinding after a stop must not wait for TIME_WAIT sockets to expire.
    socket.set_reuseaddr(true).map_err(err)?;
    socket.bind(addr).map_err(err)?;
    socket.listen(128).map_err(err)
}

impl ServerHandle {
    /// Listen on `config.bind` and serve `bank` (on the current Tokio runtime).
    pub async fn start(
        config: ServerConfig,
        bank: Arc<dyn RegisterBank>,
    ) -> Result<ServerHandle, ServerError> {
        let listener = listen(config.bind)?;
        let addr = listener.local_addr().map_err(|source| ServerError::Bind {
            addr: config.bind,
            source,
        })?;
        let inner = Arc::new(Inner {
            addr,
            allow: config.allow,
            bank,
            faults: Mutex::new(Faults::default()),
            accepted: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            requests: AtomicU64::new(0),
            exceptions: AtomicU64::new(0),
            open: AtomicU64::new(0),
            max_connections: config.max_connections.max(1),
            idle_timeout: config.idle_timeout,
            refusal_log: Mutex::new((None, 0)),
        });
        let handle = ServerHandle {
            inner,
            control: Arc::new(Control {
                task: Mutex::new(None),
            }),
        };
        handle.spawn(listener);
        Ok(handle)
    }

    /// The address actually listened on.
    pub fn local_addr(&self) -> SocketAddr {
        self.inner.addr
    }

    fn spawn(&self, listener: TcpListener) {
        let shared = self.inner.clone();
        let task = tokio::spawn(async move {
            let server = Server::new(listener);
            let on_connected = |stream: TcpStream, peer: SocketAddr| {
                let inner = shared.clone();
                async move {
                    if let Some(allow) = &inner.allow
                        && !allow.contains(&peer.ip())
                    {
                        inner.refuse(peer, "the peer is not in the allow-list");
                        return Ok(None);
                    }
                    let open = inner.open.load(Ordering::Relaxed);
                    if open >= inner.max_connections as u64 {
                        inner.refuse(
                            peer,
                            &format!("{open} connections are open, the most this server keeps"),
                        );
                        return Ok(None);
                    }
                    inner.accepted.fetch_add(1, Ordering::Relaxed);
                    if let Err(e) = stream.set_nodelay(true) {
                        tracing::debug!(%peer, error = %e, "TCP_NODELAY not set");
                    }
                    let service = Service::new(inner, peer);
                    let stream = IdleStream::new(stream, &service);
                    Ok(Some((service, stream)))
                }
            };
            let on_error = |e: io::Error| tracing::debug!(error = %e, "modbus connection ended");
            if let Err(e) = server.serve(&on_connected, on_error).await {
                tracing::warn!(error = %e, "modbus server stopped accepting");
            }
        });
        let mut slot = self.control.task.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(old) = slot.replace(task) {
            old.abort();
        }
    }

    /// Fault: stop listening and close every connection (the device is switched off).
    pub async fn stop(&self) {
        let task = self
            .control
            .task
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        if let Some(task) = task {
            task.abort();
            // Aborting drops tokio-modbus' accept loop, whose drop guard cancels every
            // connection task; wait until the listener is really closed, and (briefly) until
            // the cancelled connections are gone, so no request is answered after this returns.
            let _ = task.await;
            let until = tokio::time::Instant::now() + Duration::from_secs(1);
            while self.inner.open.load(Ordering::Relaxed) > 0 && tokio::time::Instant::now() < until
            {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
    }

    /// Listen again on the same address after [`stop`](Self::stop).
    pub async fn restart(&self) -> Result<(), ServerError> {
        self.stop().await;
        // While nobody listens, a client redialling on loopback may get the port itself as
        // its own source port (a TCP self-connection, which it drops at the first bad
        // reply): try again for a second before giving up.
        let mut tries = 0;
        let listener = loop {
            match listen(self.inner.addr) {
                Err(ServerError::Bind { source, .. })
                    if source.kind() == std::io::ErrorKind::AddrInUse && tries < 20 =>
                {
                    tries += 1;
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
                r => break r?,
            }
        };
        self.spawn(listener);
        Ok(())
    }

    /// Whether the server is listening.
    pub fn is_running(&self) -> bool {
        self.control
            .task
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .is_some_and(|t| !t.is_finished())
    }

    fn faults(&self) -> std::sync::MutexGuard<'_, Faults> {
        self.inner.faults.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Fault: delay every reply by `delay` (zero for none).
    pub fn set_delay(&self, delay: Duration) {
        self.faults().delay = delay;
    }

    /// Fault: answer every request with `exception` (`None` to stop).
    pub fn set_exception(&self, exception: Option<Exception>) {
        self.faults().exception = exception;
    }

    /// Counters.
    pub fn stats(&self) -> ServerStats {
        let i = &self.inner;
        ServerStats {
            accepted: i.accepted.load(Ordering::Relaxed),
            refused: i.refused.load(Ordering::Relaxed),
            requests: i.requests.load(Ordering::Relaxed),
            exceptions: i.exceptions.load(Ordering::Relaxed),
            open: i.open.load(Ordering::Relaxed),
        }
    }
}

/// One connection's service (counted in `Inner::open` while it exists).
struct Service {
    inner: Arc<Inner>,
    peer: SocketAddr,
    /// When the last complete request arrived (the connection's start before the first): the
    /// idle timeout counts from here.
    last_request: Arc<Mutex<Instant>>,
}

impl Service {
    fn new(inner: Arc<Inner>, peer: SocketAddr) -> Service {
        inner.open.fetch_add(1, Ordering::Relaxed);
        Service {
            inner,
            peer,
            last_request: Arc::new(Mutex::new(crate::util::clock::now())),
        }
    }
}

/// A connection's stream that ends with an error once no complete request has arrived for the
/// server's idle timeout (bytes alone do not count, so a slow writer is closed too). Without an
/// idle timeout it only passes reads and writes through.
struct IdleStream {
    stream: TcpStream,
    inner: Arc<Inner>,
    peer: SocketAddr,
    last_request: Arc<Mutex<Instant>>,
    timer: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl IdleStream {
    fn new(stream: TcpStream, service: &Service) -> Self {
        IdleStream {
            stream,
            inner: service.inner.clone(),
            peer: service.peer,
            last_request: service.last_request.clone(),
            timer: None,
        }
    }

    /// `Ready(error)` once the connection has been idle too long; otherwise the timer is set
    /// for the deadline (a later request moves it) and `Pending`.
    fn poll_idle(&mut self, cx: &mut std::task::Context<'_>) -> std::task::Poll<io::Error> {
        use std::task::Poll;
        let Some(idle) = self.inner.idle_timeout else {
            return Poll::Pending;
        };
        loop {
            let last = *self.last_request.lock().unwrap_or_else(|p| p.into_inner());
            let deadline = tokio::time::Instant::from_std(last + idle);
            if tokio::time::Instant::now() >= deadline {
                tracing::info!(
                    server = %self.inner.addr, peer = %self.peer,
                    "modbus connection closed: no request for {:.1} s (the idle timeout)",
                    idle.as_secs_f64()
                );
                return Poll::Ready(io::Error::new(
                    io::ErrorKind::TimedOut,
                    "no request within the idle timeout",
                ));
            }
            let timer = self
                .timer
                .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(deadline)));
            if timer.deadline() != deadline {
                timer.as_mut().reset(deadline);
            }
            if timer.as_mut().poll(cx).is_pending() {
                return Poll::Pending;
            }
        }
    }
}

impl tokio::io::AsyncRead for IdleStream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<io::Result<()>> {
        let this = self.get_mut();
        match Pin::new(&mut this.stream).poll_read(cx, buf) {
            std::task::Poll::Pending => this.poll_idle(cx).map(Err),
            ready => ready,
        }
    }
}

impl tokio::io::AsyncWrite for IdleStream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().stream).poll_write(cx, buf)
    }

    fn poll_flush(
        self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_flush(cx)
    }

    fn poll_shutdown(
        self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_shutdown(cx)
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        self.inner.open.fetch_sub(1, Ordering::Relaxed);
    }
}

type Reply = Result<Response, tokio_modbus::ExceptionCode>;
type Delayed = Pin<Box<dyn Future<Output = Reply> + Send>>;

impl tokio_modbus::server::Service for Service {
    type Request = SlaveRequest<'static>;
    type Response = Response;
    type Exception = tokio_modbus::ExceptionCode;
    type Future = Either<future::Ready<Reply>, Delayed>;

    fn call(&self, req: Self::Request) -> Self::Future {
        let inner = &self.inner;
        inner.requests.fetch_add(1, Ordering::Relaxed);
        *self.last_request.lock().unwrap_or_else(|p| p.into_inner()) = crate::util::clock::now();
        let faults = *inner.faults.lock().unwrap_or_else(|p| p.into_inner());
        let result = match faults.exception {
            Some(e) => Err(e),
            None => handle(inner.bank.as_ref(), req.slave, &req.request, self.peer),
        };
        if result.is_err() {
            inner.exceptions.fetch_add(1, Ordering::Relaxed);
        }
        let reply = result.map_err(tokio_modbus::ExceptionCode::from);
        if !inner.bank.responsive() {
            // A silent device: no reply; the client times out, or sees the connection close
            // when the server is stopped.
            return Either::Right(Box::pin(future::pending()));
        }
        if faults.delay.is_zero() {
            Either::Left(future::ready(reply))
        } else {
            let delay = faults.delay;
            Either::Right(Box::pin(async move {
                tokio::time::sleep(delay).await;
                reply
            }))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::borrow::Cow;

    fn peer() -> SocketAddr {
        "127.0.0.1:40000".parse().unwrap()
    }

    fn bank() -> MemoryBank {
        MemoryBank::new((0..200).collect(), vec![0; 20], Some((10, 5)))
    }

    #[test]
    fn reads_are_validated_by_us() {
        let b = bank();
        let r = |req| handle(&b, 1, &req, peer());
        assert_eq!(
            r(Request::ReadInputRegisters(3, 2)),
            Ok(Response::ReadInputRegisters(vec![3, 4]))
        );
        assert_eq!(
            r(Request::ReadInputRegisters(0, 0)),
            Err(Exception::IllegalDataValue)
        );
        assert_eq!(
            r(Request::ReadInputRegisters(0, 126)),
            Err(Exception::IllegalDataValue)
        );
        assert_eq!(
            r(Request::ReadHoldingRegisters(0, 125)),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(
            r(Request::ReadInputRegisters(150, 60)),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(
            r(Request::ReadInputRegisters(65500, 100)),
            Err(Exception::IllegalDataAddress)
        );
        assert!(r(Request::ReadInputRegisters(75, 125)).is_ok());
    }

    #[test]
    fn writes_follow_the_bank_rules() {
        let b = bank();
        let w = |req| handle(&b, 1, &req, peer());
        assert_eq!(
            w(Request::WriteSingleRegister(11, 7)),
            Ok(Response::WriteSingleRegister(11, 7))
        );
        assert_eq!(
            w(Request::WriteMultipleRegisters(12, Cow::Owned(vec![8, 9]))),
            Ok(Response::WriteMultipleRegisters(12, 2))
        );
        assert_eq!(&b.holding()[10..15], &[0, 7, 8, 9, 0]);
        assert_eq!(
            w(Request::WriteSingleRegister(9, 1)),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(
            w(Request::WriteMultipleRegisters(
                13,
                Cow::Owned(vec![1, 2, 3])
            )),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(
            w(Request::WriteMultipleRegisters(10, Cow::Owned(vec![]))),
            Err(Exception::IllegalDataValue)
        );
        assert_eq!(
            w(Request::WriteMultipleRegisters(0, Cow::Owned(vec![0; 124]))),
            Err(Exception::IllegalDataValue)
        );
    }

    #[test]
    fn unsupported_functions_are_illegal() {
        let b = bank();
        for req in [
            Request::ReadCoils(0, 1),
            Request::ReadDiscreteInputs(0, 1),
            Request::WriteSingleCoil(0, true),
            Request::MaskWriteRegister(0, 1, 2),
            Request::ReportServerId,
            Request::Custom(0x07, Cow::Owned(vec![])),
        ] {
            assert_eq!(
                handle(&b, 1, &req, peer()),
                Err(Exception::IllegalFunction),
                "{req:?}"
            );
        }
    }

    #[test]
    fn a_read_only_bank_refuses_writes() {
        struct Ro;
        impl RegisterBank for Ro {
            fn read(&self, _: u8, _: RegisterKind, r: ReadRange) -> Result<Vec<u16>, Exception> {
                Ok(vec![0; r.count() as usize + 1])
            }
        }
        assert_eq!(
            handle(&Ro, 1, &Request::WriteSingleRegister(0, 1), peer()),
            Err(Exception::IllegalFunction)
        );
        // A bank returning the wrong length is caught before the wire.
        assert_eq!(
            handle(&Ro, 1, &Request::ReadInputRegisters(0, 2), peer()),
            Err(Exception::ServerDeviceFailure)
        );
    }
}
