//! A remote CAN interface over UDP in the cannelloni v2 frame format (DESIGN §6): talks to a
//! `cannelloni` tunnel on a gateway, and is how the digital twin attaches its drive.
//!
//! Wire format (cannelloni `doc/udp_format.md`, `cannelloni.h`, `parser.cpp`; all multi-byte
//! fields big-endian). A datagram is a 5-byte header and `count` frame records:
//!
//! ```text
//! header   0      version   = 2
//!          1      op code   = 0 (DATA; 1 ACK and 2 NACK are not used over UDP)
//!          2      seq no    u8, +1 per datagram sent, wrapping
//!          3..5   count     u16, number of frame records that follow
//! record   0..4   can_id    u32 = id | EFF 0x8000_0000 | RTR 0x4000_0000 | ERR 0x2000_0000
//!          4      len       data length; bit 0x80 marks a CAN FD record
//!          5      flags     CAN FD only (absent otherwise)
//!          ..     data      `len & 0x7f` bytes; absent for an RTR record (len is then the DLC)
//! ```
//!
//! Scope: classic frames. FD records and error frames (ERR flag) are well-formed but are not
//! classic frames: they are skipped on receipt and counted in [`CannelloniStats::skipped`].
//!
//! Receiving: a datagram is validated whole before any frame is taken from it (a checked
//! view, [`wire::Packet::new_checked`]); one that fails is dropped entire and `recv` returns
//! [`CanError::Malformed`] saying what was wrong. The transport keeps working: the next `recv`
//! reads the next datagram (a malformed datagram is transient, [`CanError::is_transient`]).
//! Datagrams from an IP address other than the remote's are ignored, as cannelloni does.
//! Sequence numbers of received datagrams are tracked; gaps are counted, not acted on (UDP).
//!
//! Sending: `send` queues the frame for a writer task, which takes every frame pending when it
//! wakes and packs them, in order, into as few datagrams as fit [`MAX_DATAGRAM`] bytes, so
//! bursts (an SDO block, SYNC + RPDOs) share datagrams without the latency of cannelloni's
//! timer. [`Cannelloni::send_batch`] queues several frames at once (packed together for
//! certain). A socket error in the writer is logged and returned by the next `send`.

use super::{CanError, CanFrame, CanTransport};
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use tokio::net::UdpSocket;
use tokio::sync::{Mutex, mpsc};

/// Largest datagram we send: below the IPv6 minimum MTU (1280) less headers, and below
/// cannelloni's own 1472-byte payload and 1500-byte receive buffer, so it is never
/// fragmented and any cannelloni peer reads it whole.
pub const MAX_DATAGRAM: usize = 1200;

/// Largest datagram we accept (the whole UDP payload range; cannelloni itself sends ≤ 1472).
const RECV_BUFFER: usize = 65_536;

/// Sends (single frames or batches) that may wait for the writer task before `send` waits.
const QUEUE: usize = 1024;

/// The byte layout: named field ranges, a checked view and an encoder (smoltcp `wire` style).
pub mod wire {
    use super::super::{CanError, CanFrame};
    use std::collections::VecDeque;

    /// Protocol version carried in every datagram.
    pub const VERSION: u8 = 2;
    /// Op code of a data datagram.
    pub const OP_DATA: u8 = 0;
    /// Header length.
    pub const HEADER_LEN: usize = 5;
    /// Record length before the data for a classic frame (can_id + len).
    pub const RECORD_BASE_LEN: usize = 5;

    /// Linux `CAN_EFF_FLAG`: 29-bit identifier.
    pub const CAN_EFF_FLAG: u32 = 0x8000_0000;
    /// Linux `CAN_RTR_FLAG`: remote transmission request.
    pub const CAN_RTR_FLAG: u32 = 0x4000_0000;
    /// Linux `CAN_ERR_FLAG`: error frame.
    pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
    /// Linux `CAN_EFF_MASK`.
    pub const CAN_EFF_MASK: u32 = 0x1FFF_FFFF;
    /// Linux `CAN_SFF_MASK`.
    pub const CAN_SFF_MASK: u32 = 0x0000_07FF;
    /// cannelloni's `CANFD_FRAME` bit in the length byte.
    pub const CANFD_FRAME: u8 = 0x80;

    /// Header fields.
    pub mod field {
        use std::ops::Range;
        /// Protocol version.
        pub const VERSION: usize = 0;
        /// Op code.
        pub const OP_CODE: usize = 1;
        /// Sequence number.
        pub const SEQ_NO: usize = 2;
        /// Frame count (u16, big-endian).
        pub const COUNT: Range<usize> = 3..5;
    }

    /// Record fields, relative to the record's start.
    pub mod record {
        use std::ops::Range;
        /// can_id with flags (u32, big-endian).
        pub const CAN_ID: Range<usize> = 0..4;
        /// Length byte.
        pub const LEN: usize = 4;
        /// CAN FD flags (only when `LEN & CANFD_FRAME`).
        pub const FD_FLAGS: usize = 5;
    }

    fn malformed(msg: String) -> CanError {
        CanError::Malformed(format!("cannelloni: {msg}"))
    }

    /// One frame record as it stands in a datagram.
    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub struct Record<'a> {
        /// can_id with the EFF/RTR/ERR flag bits.
        pub can_id: u32,
        /// The length byte, FD bit included.
        pub len: u8,
        /// CAN FD flags, for an FD record.
        pub fd_flags: Option<u8>,
        /// The data bytes (empty for RTR).
        pub data: &'a [u8],
    }

    impl Record<'_> {
        /// The classic frame this record carries; `Ok(None)` for an FD record or an error
        /// frame (well-formed, not classic).
        pub fn to_frame(&self) -> Result<Option<CanFrame>, CanError> {
            if self.fd_flags.is_some() || self.can_id & CAN_ERR_FLAG != 0 {
                return Ok(None);
            }
            let extended = self.can_id & CAN_EFF_FLAG != 0;
            let id = self.can_id & CAN_EFF_MASK;
            if !extended && id > CAN_SFF_MASK {
                return Err(malformed(format!(
                    "standard can_id {:#010x} has bits above 11",
                    self.can_id
                )));
            }
            let frame = if self.can_id & CAN_RTR_FLAG != 0 {
                CanFrame::remote(id, extended, self.len)
            } else {
                CanFrame::with_id(id, extended, self.data)
            };
            // Lengths were checked by `Packet::check`; this is defensive.
            frame
                .map(Some)
                .ok_or_else(|| malformed(format!("frame {:#x}/{} invalid", self.can_id, self.len)))
        }
    }

    /// A read view of a datagram. `new_checked` validates the header and every record, so
    /// the accessors and [`Packet::records`] never index out of bounds.
    #[derive(Debug)]
    pub struct Packet<T: AsRef<[u8]>> {
        buffer: T,
    }

    impl<T: AsRef<[u8]>> Packet<T> {
        /// Wrap without checks (the accessors may then panic on short input; use
        /// `new_checked` for anything received).
        pub fn new_unchecked(buffer: T) -> Self {
            Packet { buffer }
        }

        /// Wrap and validate: version, op code, and that exactly `count` well-formed
        /// records fill the rest of the datagram.
        pub fn new_checked(buffer: T) -> Result<Self, CanError> {
            let p = Packet::new_unchecked(buffer);
            p.check()?;
            Ok(p)
        }

        /// The validation behind `new_checked`.
        pub fn check(&self) -> Result<(), CanError> {
            let b = self.buffer.as_ref();
            if b.len() < HEADER_LEN {
                return Err(malformed(format!(
                    "datagram of {} bytes is shorter than the {HEADER_LEN}-byte header",
                    b.len()
                )));
            }
            if self.version() != VERSION {
                return Err(malformed(format!(
                    "version {} (only {VERSION} is known)",
                    self.version()
                )));
            }
            if self.op_code() != OP_DATA {
                return Err(malformed(format!(
                    "op code {} is not DATA ({OP_DATA})",
                    self.op_code()
                )));
            }
            let mut at = HEADER_LEN;
            for i in 0..self.count() {
                at = record_end(b, at).map_err(|m| {
                    malformed(format!("record {i} of {} at byte {at}: {m}", self.count()))
                })?;
            }
            if at != b.len() {
                return Err(malformed(format!(
                    "{} bytes after the {} records announced",
                    b.len() - at,
                    self.count()
                )));
            }
            Ok(())
        }

        /// Protocol version.
        pub fn version(&self) -> u8 {
            self.buffer.as_ref()[field::VERSION]
        }
        /// Op code.
        pub fn op_code(&self) -> u8 {
            self.buffer.as_ref()[field::OP_CODE]
        }
        /// Sequence number.
        pub fn seq_no(&self) -> u8 {
            self.buffer.as_ref()[field::SEQ_NO]
        }
        /// Number of records.
        pub fn count(&self) -> u16 {
            let b = &self.buffer.as_ref()[field::COUNT];
            u16::from_be_bytes([b[0], b[1]])
        }

        /// The records, in order (call on a checked packet).
        pub fn records(&self) -> Records<'_> {
            Records {
                buf: self.buffer.as_ref(),
                at: HEADER_LEN,
                left: self.count(),
            }
        }
    }

    /// Where the record starting at `at` ends, or what is wrong with it.
    fn record_end(b: &[u8], at: usize) -> Result<usize, String> {
        let left = b.len().saturating_sub(at);
        if left < RECORD_BASE_LEN {
            return Err(format!(
                "{left} bytes left, a record needs {RECORD_BASE_LEN}"
            ));
        }
        let r = &b[at..];
        let can_id = u32::from_be_bytes([r[0], r[1], r[2], r[3]]);
        let len = r[record::LEN];
        let fd = len & CANFD_FRAME != 0;
        let n = (len & !CANFD_FRAME) as usize;
        let max = if fd { 64 } else { 8 };
        if n > max {
            return Err(format!(
                "length {n} exceeds {max} for a {} frame",
                if fd { "CAN FD" } else { "classic" }
            ));
        }
        let head = RECORD_BASE_LEN + usize::from(fd);
        let body = if can_id & CAN_RTR_FLAG != 0 { 0 } else { n };
        if left < head + body {
            return Err(format!(
                "{left} bytes left, the record needs {}",
                head + body
            ));
        }
        Ok(at + head + body)
    }

    /// Iterator over the records of a checked packet.
    #[derive(Debug)]
    pub struct Records<'a> {
        buf: &'a [u8],
        at: usize,
        left: u16,
    }

    impl<'a> Iterator for Records<'a> {
        type Item = Record<'a>;
        fn next(&mut self) -> Option<Record<'a>> {
            if self.left == 0 {
                return None;
            }
            let end = record_end(self.buf, self.at).ok()?;
            let r = &self.buf[self.at..end];
            self.at = end;
            self.left -= 1;
            let can_id = u32::from_be_bytes([r[0], r[1], r[2], r[3]]);
            let len = r[record::LEN];
            let (fd_flags, data_at) = if len & CANFD_FRAME != 0 {
                (Some(r[record::FD_FLAGS]), record::FD_FLAGS + 1)
            } else {
                (None, record::LEN + 1)
            };
            Some(Record {
                can_id,
                len,
                fd_flags,
                data: &r[data_at..],
            })
        }
    }

    /// Bytes `frame` takes in a datagram.
    pub fn record_len(frame: &CanFrame) -> usize {
        RECORD_BASE_LEN + frame.data().len()
    }

    /// The can_id word of `frame`, with Linux's flag bits.
    pub fn can_id_word(frame: &CanFrame) -> u32 {
        let mut w = frame.id();
        if frame.is_extended() {
            w |= CAN_EFF_FLAG;
        }
        if frame.is_remote() {
            w |= CAN_RTR_FLAG;
        }
        w
    }

    /// Append one record for `frame`.
    pub fn emit_record(frame: &CanFrame, out: &mut Vec<u8>) {
        out.extend_from_slice(&can_id_word(frame).to_be_bytes());
        out.push(frame.len() as u8);
        out.extend_from_slice(frame.data());
    }

    /// Append a header.
    pub fn emit_header(seq_no: u8, count: u16, out: &mut Vec<u8>) {
        out.extend_from_slice(&[VERSION, OP_DATA, seq_no]);
        out.extend_from_slice(&count.to_be_bytes());
    }

    /// Packs queued frames into datagrams and numbers them (sans-I/O).
    #[derive(Debug)]
    pub struct Packer {
        next_seq: u8,
        max_len: usize,
    }

    impl Packer {
        /// A packer whose datagrams stay within `max_len` bytes (at least one classic frame
        /// always fits: `max_len` is raised to 18 if lower).
        pub fn new(max_len: usize) -> Self {
            Packer {
                next_seq: 0,
                max_len: max_len.max(HEADER_LEN + RECORD_BASE_LEN + 8),
            }
        }

        /// Take frames from the front of `pending`, in order, as many as fit one datagram;
        /// `None` when nothing is pending.
        pub fn pack(&mut self, pending: &mut VecDeque<CanFrame>) -> Option<Vec<u8>> {
            if pending.is_empty() {
                return None;
            }
            let mut out = Vec::with_capacity(self.max_len);
            emit_header(self.next_seq, 0, &mut out);
            let mut count: u16 = 0;
            while let Some(f) = pending.front() {
                if out.len() + record_len(f) > self.max_len || count == u16::MAX {
                    break;
                }
                emit_record(f, &mut out);
                pending.pop_front();
                count += 1;
            }
            out[field::COUNT].copy_from_slice(&count.to_be_bytes());
            self.next_seq = self.next_seq.wrapping_add(1);
            Some(out)
        }
    }
}

/// Counters of a [`Cannelloni`] link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CannelloniStats {
    /// Datagrams sent.
    pub datagrams_sent: u64,
    /// Frames sent.
    pub frames_sent: u64,
    /// Well-formed datagrams received from the remote.
    pub datagrams_received: u64,
    /// Classic frames received.
    pub frames_received: u64,
    /// Datagrams refused as malformed.
    pub malformed: u64,
    /// Records skipped: CAN FD or error frames.
    pub skipped: u64,
    /// Datagrams ignored because they came from another address than the remote's.
    pub foreign: u64,
    /// Received sequence numbers that did not follow the previous one.
    pub seq_gaps: u64,
}

#[derive(Debug, Default)]
struct Counters {
    datagrams_sent: AtomicU64,
    frames_sent: AtomicU64,
    datagrams_received: AtomicU64,
    frames_received: AtomicU64,
    malformed: AtomicU64,
    skipped: AtomicU64,
    foreign: AtomicU64,
    seq_gaps: AtomicU64,
}

fn bump(c: &AtomicU64, n: u64) {
    c.fetch_add(n, Ordering::Relaxed);
}

/// Receive-side state: frames of the last datagram not yet returned, and the expected
/// sequence number (sans-I/O: fed with datagrams).
#[derive(Debug, Default)]
struct RxState {
    pending: VecDeque<CanFrame>,
    expected_seq: Option<u8>,
}

impl RxState {
    /// Validate and take in one datagram from the remote.
    fn handle_datagram(&mut self, bytes: &[u8], counters: &Counters) -> Result<(), CanError> {
        let packet = match wire::Packet::new_checked(bytes) {
            Ok(p) => p,
            Err(e) => {
                bump(&counters.malformed, 1);
                return Err(e);
            }
        };
        let mut frames = Vec::with_capacity(packet.count() as usize);
        let mut skipped = 0;
        for r in packet.records() {
            match r.to_frame() {
                Ok(Some(f)) => frames.push(f),
                Ok(None) => skipped += 1,
                Err(e) => {
                    bump(&counters.malformed, 1);
                    return Err(e);
                }
            }
        }
        let seq = packet.seq_no();
        if let Some(want) = self.expected_seq
            && seq != want
        {
            bump(&counters.seq_gaps, 1);
            tracing::debug!(want, got = seq, "cannelloni sequence gap");
        }
        self.expected_seq = Some(seq.wrapping_add(1));
        bump(&counters.datagrams_received, 1);
        bump(&counters.frames_received, frames.len() as u64);
        bump(&counters.skipped, skipped);
        self.pending.extend(frames);
        Ok(())
    }
}

struct RxSide {
    state: RxState,
    buf: Vec<u8>,
}

enum Outgoing {
    One(CanFrame),
    Many(Vec<CanFrame>),
}

/// One end of a cannelloni UDP tunnel.
pub struct Cannelloni {
    socket: Arc<UdpSocket>,
    remote: SocketAddr,
    tx: mpsc::Sender<Outgoing>,
    tx_error: Arc<std::sync::Mutex<Option<CanError>>>,
    rx: Mutex<RxSide>,
    counters: Arc<Counters>,
}

impl std::fmt::Debug for Cannelloni {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Cannelloni")
            .field("local", &self.socket.local_addr().ok())
            .field("remote", &self.remote)
            .finish_non_exhaustive()
    }
}

fn io_err(what: &str, e: std::io::Error) -> CanError {
    CanError::Io(format!("cannelloni: {what}: {e}"))
}

impl Cannelloni {
    /// Bind `local` (port 0 for an ephemeral one) and exchange frames with `remote`. Must be
    /// called within a tokio runtime (it starts the writer task).
    pub async fn open(local: SocketAddr, remote: SocketAddr) -> Result<Cannelloni, CanError> {
        let socket = UdpSocket::bind(local)
            .await
            .map_err(|e| io_err(&format!("bind {local}"), e))?;
        Ok(Cannelloni::with_socket(socket, remote))
    }

    /// Use an already bound socket (handed over by a supervisor, or bound early so that both
    /// ends know each other's port). Must be called within a tokio runtime.
    pub fn from_std(
        socket: std::net::UdpSocket,
        remote: SocketAddr,
    ) -> Result<Cannelloni, CanError> {
        if tokio::runtime::Handle::try_current().is_err() {
            return Err(CanError::Io(
                "cannelloni: from_std must be called within a tokio runtime".into(),
            ));
        }
        socket
            .set_nonblocking(true)
            .map_err(|e| io_err("non-blocking mode", e))?;
        let socket = UdpSocket::from_std(socket).map_err(|e| io_err("register socket", e))?;
        Ok(Cannelloni::with_socket(socket, remote))
    }

    fn with_socket(socket: UdpSocket, remote: SocketAddr) -> Cannelloni {
        let socket = Arc::new(socket);
        let (tx, rx) = mpsc::channel(QUEUE);
        let tx_error = Arc::new(std::sync::Mutex::new(None));
        let counters = Arc::new(Counters::default());
        tokio::spawn(writer(
            socket.clone(),
            remote,
            rx,
            tx_error.clone(),
            counters.clone(),
        ));
        Cannelloni {
            socket,
            remote,
            tx,
            tx_error,
            rx: Mutex::new(RxSide {
                state: RxState::default(),
                buf: vec![0; RECV_BUFFER],
            }),
            counters,
        }
    }

    /// The bound local address (with the actual port when 0 was asked for).
    pub fn local_addr(&self) -> Result<SocketAddr, CanError> {
        self.socket
            .local_addr()
            .map_err(|e| io_err("local address", e))
    }

    /// The remote's address.
    pub fn remote_addr(&self) -> SocketAddr {
        self.remote
    }

    /// Counters so far.
    pub fn stats(&self) -> CannelloniStats {
        let c = &self.counters;
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        CannelloniStats {
            datagrams_sent: g(&c.datagrams_sent),
            frames_sent: g(&c.frames_sent),
            datagrams_received: g(&c.datagrams_received),
            frames_received: g(&c.frames_received),
            malformed: g(&c.malformed),
            skipped: g(&c.skipped),
            foreign: g(&c.foreign),
            seq_gaps: g(&c.seq_gaps),
        }
    }

    /// Queue several frames at once: they go out in order, packed into as few datagrams as
    /// [`MAX_DATAGRAM`] allows (together with anything else pending).
    pub async fn send_batch(&self, frames: &[CanFrame]) -> Result<(), CanError> {
        self.take_tx_error()?;
        self.tx
            .send(Outgoing::Many(frames.to_vec()))
            .await
            .map_err(|_| CanError::Closed)
    }

    fn take_tx_error(&self) -> Result<(), CanError> {
        let e = match self.tx_error.lock() {
            Ok(mut g) => g.take(),
            Err(p) => p.into_inner().take(),
        };
        e.map_or(Ok(()), Err)
    }
}

/// The writer task: whatever is pending when it wakes goes out packed. Ends when the
/// `Cannelloni` is dropped (its sender closes), after sending what was queued.
async fn writer(
    socket: Arc<UdpSocket>,
    remote: SocketAddr,
    mut rx: mpsc::Receiver<Outgoing>,
    tx_error: Arc<std::sync::Mutex<Option<CanError>>>,
    counters: Arc<Counters>,
) {
    let mut packer = wire::Packer::new(MAX_DATAGRAM);
    let mut batch = Vec::with_capacity(64);
    let mut pending = VecDeque::new();
    while rx.recv_many(&mut batch, 64).await > 0 {
        for o in batch.drain(..) {
            match o {
                Outgoing::One(f) => pending.push_back(f),
                Outgoing::Many(v) => pending.extend(v),
            }
        }
        loop {
            let before = pending.len();
            let Some(dgram) = packer.pack(&mut pending) else {
                break;
            };
            let frames = (before - pending.len()) as u64;
            match socket.send_to(&dgram, remote).await {
                Ok(_) => {
                    bump(&counters.datagrams_sent, 1);
                    bump(&counters.frames_sent, frames);
                }
                Err(e) => {
                    let err = io_err(&format!("send to {remote}"), e);
                    tracing::warn!("{err}; {frames} frames lost");
                    match tx_error.lock() {
                        Ok(mut g) => *g = Some(err),
                        Err(p) => *p.into_inner() = Some(err),
                    }
                }
            }
        }
    }
}

impl CanTransport for Cannelloni {
    async fn send(&self, frame: &CanFrame) -> Result<(), CanError> {
        self.take_tx_error()?;
        self.tx
            .send(Outgoing::One(*frame))
            .await
            .map_err(|_| CanError::Closed)
    }

    /// Cancel-safe: frames of a datagram are stored before this returns any of them, and the
    /// only await is the socket's cancel-safe `recv_from`.
    async fn recv(&self) -> Result<CanFrame, CanError> {
        let mut guard = self.rx.lock().await;
        let side = &mut *guard;
        loop {
            if let Some(f) = side.state.pending.pop_front() {
                return Ok(f);
            }
            let (n, src) = self
                .socket
                .recv_from(&mut side.buf)
                .await
                .map_err(|e| io_err("receive", e))?;
            if src.ip() != self.remote.ip() {
                bump(&self.counters.foreign, 1);
                tracing::debug!(%src, "ignored a datagram from a stranger");
                continue;
            }
            if let Err(e) = side.state.handle_datagram(&side.buf[..n], &self.counters) {
                tracing::warn!(%src, "{e}");
                return Err(e);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::wire::{Packer, Packet};
    use super::*;

    fn malformed(bytes: &[u8]) -> String {
        match Packet::new_checked(bytes) {
            Err(CanError::Malformed(m)) => m,
            other => panic!("expected Malformed for {bytes:02x?}, got {other:?}"),
        }
    }

    fn frames_of(bytes: &[u8]) -> Vec<CanFrame> {
        let p = Packet::new_checked(bytes).unwrap();
        p.records().filter_map(|r| r.to_frame().unwrap()).collect()
    }

    #[test]
    fn one_standard_frame_encodes_to_the_spec_bytes() {
        let f = CanFrame::new(0x123, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap();
        let mut q = VecDeque::from([f]);
        let dgram = Packer::new(MAX_DATAGRAM).pack(&mut q).unwrap();
        #[rustfmt::skip]
        let want = [
            0x02,                   // version 2
            0x00,                   // op code DATA
            0x00,                   // sequence number: first datagram
            0x00, 0x01,             // count = 1, big-endian
            0x00, 0x00, 0x01, 0x23, // can_id 0x123, no flags, big-endian
            0x04,                   // len 4, FD bit clear
            0xDE, 0xAD, 0xBE, 0xEF, // data
        ];
        assert_eq!(dgram, want);
        assert!(q.is_empty());
        assert_eq!(frames_of(&want), vec![f]);
    }

    #[test]
    fn extended_remote_and_empty_frames_share_a_datagram() {
        let frames = vec![
            CanFrame::new_extended(0x1ABC_DEF0, &[0x11]).unwrap(),
            CanFrame::remote(0x701, false, 1).unwrap(),
            CanFrame::remote(0x0123_4567, true, 8).unwrap(),
            CanFrame::new(0x000, &[]).unwrap(),
        ];
        let mut packer = Packer::new(MAX_DATAGRAM);
        let mut q: VecDeque<_> = frames.iter().copied().collect();
        let dgram = packer.pack(&mut q).unwrap();
        #[rustfmt::skip]
        let want = [
            0x02, 0x00, 0x00, 0x00, 0x04, // v2, DATA, seq 0, count 4
            0x9A, 0xBC, 0xDE, 0xF0,       // 0x1ABCDEF0 | EFF 0x80000000
            0x01, 0x11,                   // len 1, data
            0x40, 0x00, 0x07, 0x01,       // 0x701 | RTR 0x40000000
            0x01,                         // DLC 1, no data bytes for RTR
            0xC1, 0x23, 0x45, 0x67,       // 0x01234567 | EFF | RTR
            0x08,                         // DLC 8, no data
            0x00, 0x00, 0x00, 0x00,       // id 0, standard
            0x00,                         // len 0
        ];
        assert_eq!(dgram, want);
        assert_eq!(frames_of(&want), frames);
        let p = Packet::new_checked(&want[..]).unwrap();
        assert_eq!(
            (p.version(), p.op_code(), p.seq_no(), p.count()),
            (2, 0, 0, 4)
        );
    }

    #[test]
    fn sequence_numbers_count_datagrams_and_wrap() {
        let mut packer = Packer::new(MAX_DATAGRAM);
        let f = CanFrame::new(1, &[]).unwrap();
        for want in (0..=255u8).chain(0..=1) {
            let d = packer.pack(&mut VecDeque::from([f])).unwrap();
            assert_eq!(d[2], want);
        }
        assert!(packer.pack(&mut VecDeque::new()).is_none());
    }

    #[test]
    fn bursts_split_at_the_datagram_limit_in_order() {
        let frames: Vec<CanFrame> = (0..200u16)
            .map(|i| CanFrame::new(i, &[i as u8; 8]).unwrap())
            .collect();
        // Independent count: 5-byte header, 13 bytes per 8-byte classic record.
        let per = (MAX_DATAGRAM - 5) / 13;
        assert_eq!(per, 91);
        let mut q: VecDeque<_> = frames.iter().copied().collect();
        let mut packer = Packer::new(MAX_DATAGRAM);
        let mut got = Vec::new();
        let mut sizes = Vec::new();
        while let Some(d) = packer.pack(&mut q) {
            assert!(d.len() <= MAX_DATAGRAM);
            let p = Packet::new_checked(&d[..]).unwrap();
            sizes.push((p.seq_no(), p.count()));
            got.extend(frames_of(&d));
        }
        assert_eq!(sizes, vec![(0, 91), (1, 91), (2, 18)]);
        assert_eq!(got, frames);
    }

    #[test]
    fn fd_and_error_records_are_skipped_not_refused() {
        #[rustfmt::skip]
        let bytes = [
            0x02, 0x00, 0x05, 0x00, 0x03, // v2, DATA, seq 5, count 3
            0x00, 0x00, 0x01, 0x23,       // FD record, id 0x123
            0x82, 0x01,                   // len 2 | CANFD_FRAME, flags BRS
            0xAA, 0xBB,
            0x20, 0x00, 0x00, 0x04,       // ERR flag | CAN_ERR_PROT class
            0x08, 0, 0, 0, 0, 0, 0, 0, 0,
            0x00, 0x00, 0x07, 0x05,       // heartbeat of node 5
            0x01, 0x7F,                   // len 1, pre-operational
        ];
        let p = Packet::new_checked(&bytes[..]).unwrap();
        let recs: Vec<_> = p.records().collect();
        assert_eq!(recs[0].fd_flags, Some(0x01));
        assert_eq!(recs[0].data, &[0xAA, 0xBB]);
        assert_eq!(recs[0].to_frame().unwrap(), None);
        assert_eq!(recs[1].to_frame().unwrap(), None);
        assert_eq!(
            frames_of(&bytes),
            vec![CanFrame::new(0x705, &[0x7F]).unwrap()]
        );

        let counters = Counters::default();
        let mut rx = RxState::default();
        rx.handle_datagram(&bytes, &counters).unwrap();
        assert_eq!(counters.skipped.load(Ordering::Relaxed), 2);
        assert_eq!(rx.pending.len(), 1);
    }

    #[test]
    fn malformed_datagrams_say_what_is_wrong() {
        assert!(malformed(&[0x02, 0x00, 0x00, 0x00]).contains("shorter than the 5-byte header"));
        assert!(malformed(&[0x03, 0x00, 0x00, 0x00, 0x00]).contains("version 3"));
        assert!(malformed(&[0x02, 0x01, 0x00, 0x00, 0x00]).contains("op code 1"));
        // count 2, one record present
        let m = malformed(&[2, 0, 0, 0, 2, 0, 0, 1, 0x23, 0]);
        assert!(m.contains("record 1 of 2 at byte 10"), "{m}");
        // len 8, three data bytes present
        let m = malformed(&[2, 0, 0, 0, 1, 0, 0, 1, 0x23, 8, 1, 2, 3]);
        assert!(m.contains("the record needs 13"), "{m}");
        // classic len 9
        let m = malformed(&[2, 0, 0, 0, 1, 0, 0, 1, 0x23, 9, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
        assert!(m.contains("length 9 exceeds 8"), "{m}");
        // FD len 65 (0x80 | 0x41)
        let m = malformed(&[2, 0, 0, 0, 1, 0, 0, 1, 0x23, 0xC1, 0]);
        assert!(m.contains("length 65 exceeds 64 for a CAN FD frame"), "{m}");
        // two bytes after the one record announced
        let m = malformed(&[2, 0, 0, 0, 1, 0, 0, 1, 0x23, 0, 0xEE, 0xEE]);
        assert!(m.contains("2 bytes after the 1 records"), "{m}");
        // well-formed layout, but a standard id with bits above 11
        let bytes = [2, 0, 0, 0, 1, 0x00, 0x00, 0x08, 0x00, 0];
        let counters = Counters::default();
        let mut rx = RxState::default();
        match rx.handle_datagram(&bytes, &counters) {
            Err(CanError::Malformed(m)) => assert!(m.contains("bits above 11"), "{m}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(counters.malformed.load(Ordering::Relaxed), 1);
        assert!(rx.pending.is_empty());
    }

    #[test]
    fn receive_state_counts_sequence_gaps() {
        let counters = Counters::default();
        let mut rx = RxState::default();
        let f = CanFrame::new(0x181, &[1]).unwrap();
        let mut packer = Packer::new(MAX_DATAGRAM);
        let d0 = packer.pack(&mut VecDeque::from([f])).unwrap();
        let _lost = packer.pack(&mut VecDeque::from([f])).unwrap();
        let d2 = packer.pack(&mut VecDeque::from([f])).unwrap();
        let d3 = packer.pack(&mut VecDeque::from([f])).unwrap();
        for d in [&d0, &d2, &d3] {
            rx.handle_datagram(d, &counters).unwrap();
        }
        assert_eq!(counters.seq_gaps.load(Ordering::Relaxed), 1);
        assert_eq!(counters.datagrams_received.load(Ordering::Relaxed), 3);
        assert_eq!(rx.pending.len(), 3);
        // an empty datagram (count 0) is valid and carries nothing
        rx.handle_datagram(&[2, 0, 4, 0, 0], &counters).unwrap();
        assert_eq!(rx.pending.len(), 3);
        assert_eq!(counters.seq_gaps.load(Ordering::Relaxed), 1);
    }
}
