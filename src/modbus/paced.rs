//! The paced reader: the acquisition's block read at a fixed rate, one wake-up per frame.
//!
//! Through the [`Link`](super::Link) task a paced frame costs two wake-ups of the runtime: the
//! tick, then the reply, and at 500 Hz the wake-ups dominate the service's CPU (on our 2-core
//! test VM a bare sleep loop costs about 40 µs per wake-up; halving the service's wake-ups cut
//! its CPU by about a fifth). So the paced reader sends the request at one tick and collects the reply
//! at the next, from a socket that is not registered with the runtime's reactor: the reply's
//! arrival wakes nobody. The reply is stamped with the kernel's receive time (`SO_TIMESTAMPNS`),
//! so a frame keeps the meaning it has through the link (the time its reply arrived) and the
//! latency statistics stay exact; publication is one period later.
//!
//! One request is outstanding at a time. A reply not in by the next tick is looked for at the
//! ticks after it (no new request goes out meanwhile), up to the per-call timeout. The guards
//! are those of the link: TCP_NODELAY; drop-and-reconnect with backoff after a transport error,
//! a timeout or a malformed or mismatched reply (a late reply can then never be taken for the
//! next one); a Modbus exception keeps the connection; the state and statistics are published
//! on the same [`Monitor`]. The framing is Modbus TCP (MBAP header + PDU, Modbus Messaging on
//! TCP/IP Implementation Guide v1.0b §3.1.3; function codes 3 and 4, Application Protocol
//! v1.1b3 §6.3–6.4), checked here byte for byte.

use super::codec::ReadRange;
use super::link::{LinkConfig, LinkError, Monitor, Redial, ReplyFault};
use super::{Exception, RegisterKind};
use std::io::{self, Write};
use std::net::TcpStream;
use std::os::fd::AsRawFd;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// A block read's reply.
#[derive(Clone, Debug, PartialEq)]
pub struct Reply {
    pub registers: Vec<u16>,
    /// When the request went out and when the reply arrived (kernel receive time).
    pub sent: Instant,
    pub at: Instant,
}

struct Pending {
    tid: u16,
    sent: Instant,
}

/// The acquisition's Modbus TCP client for one block (see the module docs). Call
/// [`tick`](Self::tick) once per period.
pub struct PacedReader {
    cfg: LinkConfig,
    kind: RegisterKind,
    unit: u8,
    range: ReadRange,
    sock: Option<TcpStream>,
    buf: Vec<u8>,
    pending: Option<Pending>,
    tid: u16,
    redial: Redial,
}

impl PacedReader {
    /// A reader of `range` (`kind`, unit `unit`) on the device in `cfg`; it connects at the
    /// first tick.
    pub fn new(
        cfg: LinkConfig,
        kind: RegisterKind,
        unit: u8,
        range: ReadRange,
    ) -> (PacedReader, Monitor) {
        let (redial, monitor) = Redial::new(&cfg);
        (
            PacedReader {
                cfg,
                kind,
                unit,
                range,
                sock: None,
                buf: Vec::with_capacity(9 + 2 * range.count() as usize),
                pending: None,
                tid: 0,
                redial,
            },
            monitor,
        )
    }

    /// One period: collect the outstanding reply if it is in, then send the next request.
    /// `None` while a reply is still awaited. While the link is down this waits for the next
    /// connection attempt (the backoff) and returns its error if it fails.
    pub async fn tick(&mut self) -> Option<Result<Reply, LinkError>> {
        if self.sock.is_none()
            && let Err(e) = self.connect().await
        {
            return Some(Err(e));
        }
        let mut out = None;
        if let Some(sent) = self.pending.as_ref().map(|p| p.sent) {
            let collected = self.collect();
            let now = crate::util::clock::now();
            let outcome = match collected {
                Ok(None) if now.saturating_duration_since(sent) < self.cfg.timeout => {
                    return None;
                }
                Ok(None) => Err(LinkError::Timeout(self.cfg.timeout)),
                // A wall-clock step between the kernel's stamp and now could move the stamp:
                // a reply arrives after its request and before it is read.
                Ok(Some((registers, at))) => Ok(Reply {
                    registers,
                    sent,
                    at: at.map_or(now, |a| a.clamp(sent, now)),
                }),
                Err(e) => Err(e),
            };
            let at = outcome.as_ref().map(|r| r.at).unwrap_or(now);
            self.redial.record(&outcome, sent, at);
            self.pending = None;
            if let Err(e) = &outcome
                && e.drops_connection()
            {
                self.fail(*e);
                return Some(outcome);
            }
            out = Some(outcome);
        }
        if let Err(e) = self.send() {
            let now = crate::util::clock::now();
            self.redial.record::<()>(&Err(e), now, now);
            self.fail(e);
            // A reply collected this tick is still good; the send error shows next time.
            return out.or(Some(Err(e)));
        }
        out
    }

    async fn connect(&mut self) -> Result<(), LinkError> {
        let stream = self.redial.dial(&self.cfg).await?;
        match off_reactor(stream) {
            Ok(sock) => {
                self.sock = Some(sock);
                self.buf.clear();
                Ok(())
            }
            Err(e) => {
                self.fail(e);
                Err(e)
            }
        }
    }

    /// Drop the connection (a late reply can no longer be misread) and schedule a reconnect.
    fn fail(&mut self, error: LinkError) {
        self.sock = None;
        self.pending = None;
        self.buf.clear();
        self.redial.down(error);
    }

    fn send(&mut self) -> Result<(), LinkError> {
        let Some(sock) = self.sock.as_mut() else {
            return Ok(());
        };
        self.tid = self.tid.wrapping_add(1);
        let adu = encode_read(self.tid, self.unit, self.kind, self.range);
        let sent = crate::util::clock::now();
        match sock.write(&adu) {
            Ok(n) if n == adu.len() => {}
            // Twelve bytes into an empty send buffer: anything less means the socket is stuck.
            Ok(_) => return Err(LinkError::Io(io::ErrorKind::WriteZero)),
            Err(e) => return Err(LinkError::Io(e.kind())),
        }
        self.pending = Some(Pending {
            tid: self.tid,
            sent,
        });
        Ok(())
    }

    /// Take what has arrived; the reply's registers and receive time once it is complete.
    #[allow(clippy::type_complexity)]
    fn collect(&mut self) -> Result<Option<(Vec<u16>, Option<Instant>)>, LinkError> {
        let (Some(sock), Some(p)) = (self.sock.as_ref(), self.pending.as_ref()) else {
            return Ok(None);
        };
        let mut stamp = None;
        let mut chunk = [0u8; 512];
        // Read until the reply is complete or nothing more is there (usually one call).
        loop {
            match decode_read(&self.buf, p.tid, self.unit, self.kind, self.range) {
                Ok(None) => {}
                // A whole reply (bytes after it fail the decode), good or not: consumed.
                Ok(Some(regs)) => {
                    self.buf.clear();
                    return Ok(Some((regs, stamp.map(instant_of))));
                }
                Err(e) => {
                    self.buf.clear();
                    return Err(e);
                }
            }
            match recv_stamped(sock, &mut chunk) {
                Ok((0, _)) => return Err(LinkError::Io(io::ErrorKind::UnexpectedEof)),
                Ok((n, t)) => {
                    self.buf.extend_from_slice(&chunk[..n]);
                    stamp = t.or(stamp);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(None),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(LinkError::Io(e.kind())),
            }
        }
    }
}

/// The connection as a non-blocking std socket stamping what it receives.
fn off_reactor(stream: tokio::net::TcpStream) -> Result<TcpStream, LinkError> {
    let connect = |e: io::Error| LinkError::Connect(e.kind());
    // Off the reactor: the reply's arrival must not wake the runtime. It stays non-blocking.
    let sock = stream.into_std().map_err(connect)?;
    sock.set_nonblocking(true).map_err(connect)?;
    crate::util::sock::set_int(&sock, libc::SOL_SOCKET, libc::SO_TIMESTAMPNS, 1)
        .map_err(connect)?;
    Ok(sock)
}

/// The request ADU: MBAP header (transaction id, protocol 0, length 6, unit) and the PDU
/// (function 3 or 4, start address, quantity).
pub fn encode_read(tid: u16, unit: u8, kind: RegisterKind, range: ReadRange) -> [u8; 12] {
    let [t0, t1] = tid.to_be_bytes();
    let [a0, a1] = range.start().to_be_bytes();
    let [c0, c1] = range.count().to_be_bytes();
    [t0, t1, 0, 0, 0, 6, unit, function(kind), a0, a1, c0, c1]
}

fn function(kind: RegisterKind) -> u8 {
    match kind {
        RegisterKind::Holding => 3,
        RegisterKind::Input => 4,
    }
}

/// A reply ADU in `buf`: `None` while incomplete; the registers; or what is wrong with it
/// (an exception reply is [`LinkError::Exception`]; bytes beyond one reply are malformed).
pub fn decode_read(
    buf: &[u8],
    tid: u16,
    unit: u8,
    kind: RegisterKind,
    range: ReadRange,
) -> Result<Option<Vec<u16>>, LinkError> {
    let Some(total) = reply_len(buf)? else {
        return Ok(None);
    };
    if buf.len() < total {
        return Ok(None);
    }
    if buf.len() > total {
        return Err(LinkError::InvalidReply(ReplyFault::Malformed));
    }
    let data = read_reply(buf, tid, unit, kind, range)?;
    Ok(Some(
        data.chunks_exact(2)
            .map(|w| u16::from_be_bytes([w[0], w[1]]))
            .collect(),
    ))
}

/// The length of the ADU that starts `buf` (MBAP header: protocol 0, length 2..=254), `None`
/// while its header is incomplete. The ADU itself may still be incomplete.
pub fn reply_len(buf: &[u8]) -> Result<Option<usize>, LinkError> {
    if buf.len() < 7 {
        return Ok(None);
    }
    let len = u16::from_be_bytes([buf[4], buf[5]]) as usize;
    if u16::from_be_bytes([buf[2], buf[3]]) != 0 || !(2..=254).contains(&len) {
        return Err(LinkError::InvalidReply(ReplyFault::Malformed));
    }
    Ok(Some(6 + len))
}

/// The register bytes (big-endian, two per register) of `adu`, one whole reply ADU (as long
/// as [`reply_len`] says) to the read of `range` with transaction id `tid`; or what is wrong
/// with it (an exception reply is [`LinkError::Exception`]).
pub fn read_reply(
    adu: &[u8],
    tid: u16,
    unit: u8,
    kind: RegisterKind,
    range: ReadRange,
) -> Result<&[u8], LinkError> {
    let bad = |f| Err(LinkError::InvalidReply(f));
    if adu.len() < 8 || reply_len(adu)? != Some(adu.len()) {
        return bad(ReplyFault::Malformed);
    }
    if u16::from_be_bytes([adu[0], adu[1]]) != tid || adu[6] != unit {
        return bad(ReplyFault::Header);
    }
    let fc = function(kind);
    let pdu = &adu[7..];
    match pdu[0] {
        f if f == fc | 0x80 => match pdu {
            [_, code] => Err(LinkError::Exception(Exception::from_code(*code))),
            _ => bad(ReplyFault::Malformed),
        },
        f if f == fc => {
            let expected = range.count();
            let Some(&bytes) = pdu.get(1) else {
                return bad(ReplyFault::Malformed);
            };
            let data = &pdu[2..];
            if bytes as usize != data.len() || !data.len().is_multiple_of(2) {
                return bad(ReplyFault::Malformed);
            }
            if data.len() != 2 * expected as usize {
                return bad(ReplyFault::Count {
                    expected,
                    got: data.len() / 2,
                });
            }
            Ok(data)
        }
        _ => bad(ReplyFault::Function),
    }
}

/// `recvmsg` without blocking: the bytes read and the kernel's receive time of the data
/// (`SCM_TIMESTAMPNS`, CLOCK_REALTIME), if it came with it.
fn recv_stamped(sock: &TcpStream, buf: &mut [u8]) -> io::Result<(usize, Option<SystemTime>)> {
    let mut iov = libc::iovec {
        iov_base: buf.as_mut_ptr().cast(),
        iov_len: buf.len(),
    };
    // Room for one timespec control message, aligned for cmsghdr.
    let mut control = [0u64; 8];
    // SAFETY: msghdr is plain data; every pointer set below outlives the call.
    let mut msg: libc::msghdr = unsafe { std::mem::zeroed() };
    msg.msg_iov = &mut iov;
    msg.msg_iovlen = 1;
    msg.msg_control = control.as_mut_ptr().cast();
    msg.msg_controllen = std::mem::size_of_val(&control) as _;
    // SAFETY: `msg` describes `buf` and `control`, both valid for writes of their lengths.
    let n = unsafe { libc::recvmsg(sock.as_raw_fd(), &mut msg, libc::MSG_DONTWAIT) };
    if n < 0 {
        return Err(io::Error::last_os_error());
    }
    let mut stamp = None;
    // SAFETY: the CMSG_* walk stays within `msg.msg_controllen` bytes of `control`, as the
    // kernel filled them; the timespec is read unaligned.
    unsafe {
        let mut c = libc::CMSG_FIRSTHDR(&msg);
        while !c.is_null() {
            if (*c).cmsg_level == libc::SOL_SOCKET && (*c).cmsg_type == libc::SCM_TIMESTAMPNS {
                let t: libc::timespec = std::ptr::read_unaligned(libc::CMSG_DATA(c).cast());
                if let (Ok(s), Ok(ns)) = (u64::try_from(t.tv_sec), u32::try_from(t.tv_nsec)) {
                    stamp = Some(UNIX_EPOCH + Duration::new(s, ns));
                }
            }
            c = libc::CMSG_NXTHDR(&msg, c);
        }
    }
    Ok((n as usize, stamp))
}

/// The monotonic instant of a CLOCK_REALTIME time in the recent past.
fn instant_of(t: SystemTime) -> Instant {
    let (now, wall) = (crate::util::clock::now(), SystemTime::now());
    match wall.duration_since(t) {
        Ok(ago) => now.checked_sub(ago).unwrap_or(now),
        // Stamped "in the future" (the wall clock stepped back): take now.
        Err(_) => now,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(start: u16, count: u16) -> ReadRange {
        ReadRange::new(start, count).expect("range")
    }

    #[test]
    fn the_request_is_the_spec_adu() {
        // Implementation Guide §3.1.3 / Application Protocol §6.4: tid, protocol 0, length
        // 6, unit, function 4, start 0x006B, quantity 3.
        assert_eq!(
            encode_read(0x1234, 7, RegisterKind::Input, range(0x6B, 3)),
            [0x12, 0x34, 0, 0, 0, 6, 7, 4, 0x00, 0x6B, 0x00, 0x03]
        );
        assert_eq!(
            encode_read(1, 1, RegisterKind::Holding, range(0, 125))[7..],
            [3, 0, 0, 0, 125]
        );
    }

    #[test]
    fn replies_decode_and_faults_are_named() {
        let r = range(0x6B, 3);
        let ok = [
            0x12, 0x34, 0, 0, 0, 9, 7, 4, 6, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64,
        ];
        assert_eq!(
            decode_read(&ok, 0x1234, 7, RegisterKind::Input, r),
            Ok(Some(vec![0x022B, 0, 0x64]))
        );
        // Incomplete: wait for the rest.
        for cut in [0, 6, 7, 14] {
            assert_eq!(
                decode_read(&ok[..cut], 0x1234, 7, RegisterKind::Input, r),
                Ok(None)
            );
        }
        let fault = |b: &[u8]| decode_read(b, 0x1234, 7, RegisterKind::Input, r);
        let mut other_tid = ok;
        other_tid[1] = 0x35;
        assert_eq!(
            fault(&other_tid),
            Err(LinkError::InvalidReply(ReplyFault::Header))
        );
        let mut other_unit = ok;
        other_unit[6] = 8;
        assert_eq!(
            fault(&other_unit),
            Err(LinkError::InvalidReply(ReplyFault::Header))
        );
        let mut fc3 = ok;
        fc3[7] = 3;
        assert_eq!(
            fault(&fc3),
            Err(LinkError::InvalidReply(ReplyFault::Function))
        );
        let mut extra = ok.to_vec();
        extra.push(0);
        assert_eq!(
            fault(&extra),
            Err(LinkError::InvalidReply(ReplyFault::Malformed))
        );
        // Two registers where three were asked for.
        let short = [0x12, 0x34, 0, 0, 0, 7, 7, 4, 4, 0, 1, 0, 2];
        assert_eq!(
            fault(&short),
            Err(LinkError::InvalidReply(ReplyFault::Count {
                expected: 3,
                got: 2
            }))
        );
        // Exception 02 (illegal data address) to function 4.
        let exc = [0x12, 0x34, 0, 0, 0, 3, 7, 0x84, 0x02];
        assert_eq!(
            fault(&exc),
            Err(LinkError::Exception(Exception::from_code(2)))
        );
    }
}
