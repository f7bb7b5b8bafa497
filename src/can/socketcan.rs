//! SocketCAN (production): a Linux `CAN_RAW` socket on a CAN interface, over the `socketcan`
//! crate's tokio support.
//!
//! Scope and kernel options, set explicitly rather than trusted as defaults:
//! - classic frames only: the socket is a plain `CAN_RAW` socket without
//!   `CAN_RAW_FD_FRAMES`, so the kernel never delivers CAN FD frames to it (they are filtered
//!   out in the kernel, not refused here);
//! - error frames: the error mask is 0, so the kernel sends none; one that still arrives is
//!   skipped;
//! - `CAN_RAW_LOOPBACK` on (the kernel default): other sockets on this host, e.g. a twin or
//!   candump on the same interface, see our frames as they would on the wire;
//! - `CAN_RAW_RECV_OWN_MSGS` off (the kernel default): this socket does not get its own frames
//!   back, as [`CanTransport::recv`] requires.
//!
//! A full transmit queue (`ENOBUFS`, common on real controllers with a short `txqueuelen`) is
//! retried for a while before `send` reports it.

use super::{CanError, CanFrame, CanTransport};
use ::socketcan::{EmbeddedFrame, ExtendedId, Id, SocketOptions, StandardId};
use std::io;
use std::time::Duration;

/// How often, and how far apart, a send that met a full transmit queue is retried (at
/// 125 kbit/s a classic frame takes about 1 ms on the wire).
const ENOBUFS_RETRIES: u32 = 200;
const ENOBUFS_PAUSE: Duration = Duration::from_millis(1);

/// A CAN_RAW socket bound to one interface.
#[derive(Debug)]
pub struct SocketCan {
    sock: ::socketcan::tokio::CanSocket,
    ifname: String,
}

impl SocketCan {
    /// Open `ifname` (e.g. `can0`, `vcan0`). Must be called within a tokio runtime.
    pub fn open(ifname: &str) -> Result<SocketCan, CanError> {
        if tokio::runtime::Handle::try_current().is_err() {
            return Err(CanError::Io(format!(
                "{ifname}: SocketCan::open must be called within a tokio runtime"
            )));
        }
        let err = |what: &str, e: io::Error| CanError::Io(format!("{ifname}: {what}: {e}"));
        let sock = ::socketcan::tokio::CanSocket::open(ifname).map_err(|e| err("open", e))?;
        sock.set_error_filter(0).map_err(|e| err("error mask", e))?;
        sock.set_loopback(true).map_err(|e| err("loopback", e))?;
        sock.set_recv_own_msgs(false)
            .map_err(|e| err("recv_own_msgs", e))?;
        Ok(SocketCan {
            sock,
            ifname: ifname.to_owned(),
        })
    }

    /// The interface name.
    pub fn ifname(&self) -> &str {
        &self.ifname
    }

    fn io(&self, what: &str, e: io::Error) -> CanError {
        CanError::Io(format!("{}: {what}: {e}", self.ifname))
    }
}

/// Our frame as the kernel's.
pub fn to_kernel(frame: &CanFrame) -> Result<::socketcan::CanFrame, CanError> {
    let id = if frame.is_extended() {
        ExtendedId::new(frame.id()).map(Id::Extended)
    } else {
        u16::try_from(frame.id())
            .ok()
            .and_then(StandardId::new)
            .map(Id::Standard)
    };
    let bad = || CanError::Malformed(format!("frame {frame} does not fit a classic CAN frame"));
    let id = id.ok_or_else(bad)?;
    let k = if frame.is_remote() {
        ::socketcan::CanFrame::new_remote(id, frame.len())
    } else {
        ::socketcan::CanFrame::new(id, frame.data())
    };
    k.ok_or_else(bad)
}

/// The kernel's frame as ours; `None` for an error frame.
pub fn from_kernel(k: &::socketcan::CanFrame) -> Option<CanFrame> {
    let (id, extended) = match k.id() {
        Id::Standard(s) => (u32::from(s.as_raw()), false),
        Id::Extended(e) => (e.as_raw(), true),
    };
    match k {
        ::socketcan::CanFrame::Data(d) => CanFrame::with_id(id, extended, d.data()),
        ::socketcan::CanFrame::Remote(r) => {
            CanFrame::remote(id, extended, u8::try_from(r.dlc()).ok()?)
        }
        ::socketcan::CanFrame::Error(_) => None,
    }
}

impl CanTransport for SocketCan {
    async fn send(&self, frame: &CanFrame) -> Result<(), CanError> {
        let k = to_kernel(frame)?;
        let mut tries = 0;
        loop {
            match self.sock.write_frame(k).await {
                Ok(()) => return Ok(()),
                Err(e) if e.raw_os_error() == Some(libc::ENOBUFS) && tries < ENOBUFS_RETRIES => {
                    tries += 1;
                    tokio::time::sleep(ENOBUFS_PAUSE).await;
                }
                Err(e) => return Err(self.io("send", e)),
            }
        }
    }

    /// Cancel-safe: `read_frame` reads inside the readiness poll, so a dropped future has
    /// taken nothing from the socket.
    async fn recv(&self) -> Result<CanFrame, CanError> {
        loop {
            let k = self
                .sock
                .read_frame()
                .await
                .map_err(|e| self.io("receive", e))?;
            match from_kernel(&k) {
                Some(f) => return Ok(f),
                None => tracing::debug!(iface = %self.ifname, "skipped an error frame"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ::socketcan::Frame;

    #[test]
    fn frames_convert_both_ways_with_linux_id_words() {
        let cases = [
            (CanFrame::new(0x123, &[1, 2, 3]).unwrap(), 0x0000_0123),
            (
                CanFrame::new_extended(0x1ABC_DEF0, &[0xFF]).unwrap(),
                0x9ABC_DEF0, // | CAN_EFF_FLAG
            ),
            (CanFrame::remote(0x701, false, 1).unwrap(), 0x4000_0701), // | CAN_RTR_FLAG
            (CanFrame::remote(0x1234, true, 8).unwrap(), 0xC000_1234), // | EFF | RTR
        ];
        for (f, word) in cases {
            let k = to_kernel(&f).unwrap();
            assert_eq!(k.id_word(), word, "{f:?}");
            assert_eq!(k.dlc(), f.len(), "{f:?}");
            assert_eq!(from_kernel(&k), Some(f));
        }
    }

    #[test]
    fn error_frames_are_not_ours() {
        let e = ::socketcan::CanFrame::Error(
            ::socketcan::CanErrorFrame::new_error(0x004, &[0; 8]).unwrap(),
        );
        assert_eq!(from_kernel(&e), None);
    }

    #[test]
    fn open_outside_a_runtime_is_an_error_not_a_panic() {
        match SocketCan::open("vcan0") {
            Err(CanError::Io(m)) => assert!(m.contains("tokio runtime"), "{m}"),
            other => panic!("{other:?}"),
        }
    }
}
