//! The pipelined reader: the acquisition's block read as fast as the module answers, with
//! several requests in flight.
//!
//! Unthrottled, a read through the [`Link`](super::Link) task costs a queue, a task switch and
//! a timer per frame, and one whole round trip during which neither side works on the next
//! one: the service's own work per frame adds to the module's instead of overlapping it. A
//! Modbus TCP client may have several transactions outstanding on one connection (the
//! transaction id matches a reply to its request; Modbus Messaging on TCP/IP Implementation
//! Guide v1.0b §3.1.3 and §4.2), so this reader keeps `depth` block reads in flight: while the
//! service decodes and publishes one frame the module is already answering the next, and one
//! `read` from the socket usually brings several replies. Each reply is matched to its request
//! by transaction id and decoded in place: the receive buffer, the request buffer and the
//! registers are reused, nothing is allocated per frame.
//!
//! The guards are those of the link: TCP_NODELAY; a per-request timeout (the oldest request
//! in flight is answered within the link's timeout, or the connection is dropped);
//! drop-and-reconnect with backoff after a transport error, a timeout or a malformed or
//! unmatched reply (a late reply can then never be taken for another one); a Modbus exception
//! keeps the connection; the state and statistics are published on the same [`Monitor`]. A
//! module that takes one request at a time still works with depth 1 (the classic client).
//! The framing and the reply checks are those of the paced reader ([`super::paced`]).

use super::RegisterKind;
use super::codec::ReadRange;
use super::link::{LinkConfig, LinkError, Monitor, Redial, ReplyFault};
use super::paced::{encode_read, read_reply, reply_len};
use std::collections::VecDeque;
use std::io;
use std::time::Instant;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

/// Requests in flight by default: one, as every module takes. pymodbus 3.16's server, for one,
/// now and then drops a request that arrives behind another (2 timeouts in 6111 reads at
/// depth 4); the twin's module takes 4 (configs/twin-service.toml).
pub const DEFAULT_DEPTH: usize = 1;
/// The most requests in flight allowed.
pub const MAX_DEPTH: usize = 16;
/// The longest Modbus TCP ADU (MBAP header and 253-byte PDU).
const MAX_ADU: usize = 260;
/// The receive buffer: room for every reply in flight at the deepest pipeline, twice.
const RX_BUF: usize = 2 * MAX_DEPTH * MAX_ADU;

/// A block read's reply, its registers borrowed from the reader until the next call.
#[derive(Debug, PartialEq)]
pub struct Block<'a> {
    pub registers: &'a [u16],
    /// When the request went out and when its reply was read from the socket.
    pub sent: Instant,
    pub at: Instant,
}

#[derive(Clone, Copy)]
struct Pending {
    tid: u16,
    sent: Instant,
}

/// The acquisition's Modbus TCP client for one block, `depth` requests in flight (see the
/// module docs). Call [`next`](Self::next) in a loop.
pub struct PipelinedReader {
    cfg: LinkConfig,
    kind: RegisterKind,
    unit: u8,
    range: ReadRange,
    depth: usize,
    sock: Option<TcpStream>,
    rx: Box<[u8]>,
    head: usize,
    tail: usize,
    tx: Vec<u8>,
    pending: VecDeque<Pending>,
    tid: u16,
    registers: Vec<u16>,
    /// When the last bytes were read from the socket.
    read_at: Instant,
    redial: Redial,
}

impl PipelinedReader {
    /// A reader of `range` (`kind`, unit `unit`) on the device in `cfg` with `depth` requests
    /// in flight (clamped to 1..=[`MAX_DEPTH`]); it connects at the first call.
    pub fn new(
        cfg: LinkConfig,
        kind: RegisterKind,
        unit: u8,
        range: ReadRange,
        depth: usize,
    ) -> (PipelinedReader, Monitor) {
        let (redial, monitor) = Redial::new(&cfg);
        let depth = depth.clamp(1, MAX_DEPTH);
        (
            PipelinedReader {
                cfg,
                kind,
                unit,
                range,
                depth,
                sock: None,
                rx: vec![0; RX_BUF].into_boxed_slice(),
                head: 0,
                tail: 0,
                tx: Vec::with_capacity(12 * depth),
                pending: VecDeque::with_capacity(depth),
                tid: 0,
                registers: vec![0; range.count() as usize],
                read_at: crate::util::clock::now(),
                redial,
            },
            monitor,
        )
    }

    /// Requests kept in flight.
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// The next reply, in the order the module answers. While the link is down this waits for
    /// the next connection attempt (the backoff) and returns its error if it fails; a
    /// transport error, a timeout or a bad reply drops the connection and is returned; an
    /// exception reply is returned and the connection kept.
    pub async fn next(&mut self) -> Result<Block<'_>, LinkError> {
        let (sent, at) = self.next_reply().await?;
        Ok(Block {
            registers: &self.registers,
            sent,
            at,
        })
    }

    async fn next_reply(&mut self) -> Result<(Instant, Instant), LinkError> {
        loop {
            if self.sock.is_none() {
                self.connect().await?;
            }
            if let Err(e) = self.top_up().await {
                let now = crate::util::clock::now();
                self.redial.record::<()>(&Err(e), now, now);
                return Err(self.fail(e));
            }
            match self.take() {
                Ok(None) => {}
                Ok(Some((sent, at))) => {
                    self.redial.record::<()>(&Ok(()), sent, at);
                    return Ok((sent, at));
                }
                Err((e, sent)) => {
                    let now = crate::util::clock::now();
                    self.redial.record::<()>(&Err(e), sent, now);
                    return Err(if e.drops_connection() {
                        self.fail(e)
                    } else {
                        e
                    });
                }
            }
            if let Err(e) = self.fill().await {
                let now = crate::util::clock::now();
                let sent = self.pending.front().map_or(now, |p| p.sent);
                self.redial.record::<()>(&Err(e), sent, now);
                return Err(self.fail(e));
            }
        }
    }

    async fn connect(&mut self) -> Result<(), LinkError> {
        let stream = self.redial.dial(&self.cfg).await?;
        self.sock = Some(stream);
        self.head = 0;
        self.tail = 0;
        self.pending.clear();
        Ok(())
    }

    /// Drop the connection (a late reply can no longer be misread) and schedule a reconnect.
    fn fail(&mut self, error: LinkError) -> LinkError {
        self.sock = None;
        self.pending.clear();
        self.head = 0;
        self.tail = 0;
        self.redial.down(error)
    }

    /// Send requests until `depth` are in flight (one write for all of them).
    async fn top_up(&mut self) -> Result<(), LinkError> {
        let missing = self.depth.saturating_sub(self.pending.len());
        let Some(sock) = self.sock.as_mut() else {
            return Ok(());
        };
        if missing == 0 {
            return Ok(());
        }
        self.tx.clear();
        let first = self.tid;
        for k in 1..=missing {
            let tid = first.wrapping_add(k as u16);
            self.tx
                .extend_from_slice(&encode_read(tid, self.unit, self.kind, self.range));
        }
        let sent = crate::util::clock::now();
        // At most `MAX_DEPTH` × 12 bytes outstanding: the send buffer never holds them back
        // for long, and a module that stops reading shows as the oldest request's timeout.
        match tokio::time::timeout(self.cfg.timeout, sock.write_all(&self.tx)).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(LinkError::Io(e.kind())),
            Err(_) => return Err(LinkError::Timeout(self.cfg.timeout)),
        }
        for k in 1..=missing {
            self.pending.push_back(Pending {
                tid: first.wrapping_add(k as u16),
                sent,
            });
        }
        self.tid = first.wrapping_add(missing as u16);
        Ok(())
    }

    /// Take one whole reply from the receive buffer into `registers`: when its request was
    /// sent and when it was read from the socket; `None` while no whole reply is in. A reply
    /// must answer a request in flight (by transaction id: modules answer in order, but the
    /// id decides); it is consumed, good or not.
    #[allow(clippy::type_complexity)]
    fn take(&mut self) -> Result<Option<(Instant, Instant)>, (LinkError, Instant)> {
        let buf = &self.rx[self.head..self.tail];
        let len = match reply_len(buf) {
            Ok(Some(len)) if buf.len() >= len => len,
            Ok(_) => return Ok(None),
            Err(e) => return Err((e, self.read_at)),
        };
        let adu = &buf[..len];
        let tid = u16::from_be_bytes([adu[0], adu[1]]);
        let Some(p) = self
            .pending
            .iter()
            .position(|p| p.tid == tid)
            .and_then(|k| self.pending.remove(k))
        else {
            return Err((LinkError::InvalidReply(ReplyFault::Header), self.read_at));
        };
        let decoded = read_reply(adu, tid, self.unit, self.kind, self.range).map(|data| {
            for (r, w) in self.registers.iter_mut().zip(data.chunks_exact(2)) {
                *r = u16::from_be_bytes([w[0], w[1]]);
            }
        });
        self.head += len;
        if self.head == self.tail {
            self.head = 0;
            self.tail = 0;
        }
        match decoded {
            Ok(()) => Ok(Some((p.sent, self.read_at.max(p.sent)))),
            Err(e) => Err((e, p.sent)),
        }
    }

    /// Read what has arrived, waiting for it up to the oldest request's deadline.
    async fn fill(&mut self) -> Result<(), LinkError> {
        if self.rx.len() - self.tail < MAX_ADU {
            self.rx.copy_within(self.head..self.tail, 0);
            self.tail -= self.head;
            self.head = 0;
        }
        let Some(sock) = self.sock.as_ref() else {
            return Err(LinkError::Disconnected);
        };
        let deadline =
            self.pending.front().map_or_else(Instant::now, |p| p.sent) + self.cfg.timeout;
        loop {
            match sock.try_read(&mut self.rx[self.tail..]) {
                Ok(0) => return Err(LinkError::Io(io::ErrorKind::UnexpectedEof)),
                Ok(n) => {
                    self.tail += n;
                    self.read_at = crate::util::clock::now();
                    return Ok(());
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(LinkError::Io(e.kind())),
            }
            match tokio::time::timeout_at(tokio::time::Instant::from_std(deadline), sock.readable())
                .await
            {
                Ok(Ok(())) => {}
                Ok(Err(e)) => return Err(LinkError::Io(e.kind())),
                Err(_) => return Err(LinkError::Timeout(self.cfg.timeout)),
            }
        }
    }
}
