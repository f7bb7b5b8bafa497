//! CAN frames and the transports that carry them (DESIGN §6): one trait, several carriers.
//!
//! - `socketcan`: a Linux CAN_RAW socket (production; tested against vcan in a VM);
//! - `cannelloni`: a remote CAN interface over UDP in the cannelloni v2 frame format (a
//!   gateway; also how the digital twin connects);
//! - `pycan`: python-can's `udp_multicast` bus, so python-can / python-canopen rigs share a bus
//!   with us (its MessagePack subset is in `msgpack`);
//! - `memory`: an in-process bus for unit tests and the in-process twin;
//! - `fault`: a wrapper around any of these that drops, delays, or cuts the link, for the
//!   reliability tests.
//!
//! A transport moves classic CAN frames (11- or 29-bit identifiers, up to 8 data bytes). Its
//! methods take `&self`, so a driver task can wait for a frame in one `select!` branch and
//! send from another; `recv` is cancel-safe (dropping its future loses no frame).

pub mod cannelloni;
pub mod fault;
pub mod memory;
pub mod msgpack;
pub mod pycan;
pub mod socketcan;

use std::fmt;
use std::future::Future;
use thiserror::Error;

/// Largest standard (11-bit) identifier.
pub const MAX_STANDARD_ID: u32 = 0x7FF;
/// Largest extended (29-bit) identifier.
pub const MAX_EXTENDED_ID: u32 = 0x1FFF_FFFF;

/// A classic CAN frame.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct CanFrame {
    id: u32,
    extended: bool,
    rtr: bool,
    len: u8,
    data: [u8; 8],
}

impl CanFrame {
    /// A data frame with a standard identifier; `None` if the id exceeds 11 bits or the data
    /// exceeds 8 bytes.
    pub fn new(id: u16, data: &[u8]) -> Option<Self> {
        Self::with_id(id as u32, false, data)
    }

    /// A data frame with an extended (29-bit) identifier.
    pub fn new_extended(id: u32, data: &[u8]) -> Option<Self> {
        Self::with_id(id, true, data)
    }

    /// A data frame with the given identifier kind.
    pub fn with_id(id: u32, extended: bool, data: &[u8]) -> Option<Self> {
        let max = if extended {
            MAX_EXTENDED_ID
        } else {
            MAX_STANDARD_ID
        };
        if id > max || data.len() > 8 {
            return None;
        }
        let mut d = [0u8; 8];
        d[..data.len()].copy_from_slice(data);
        Some(CanFrame {
            id,
            extended,
            rtr: false,
            len: data.len() as u8,
            data: d,
        })
    }

    /// A remote-transmission-request frame asking for `len` bytes.
    pub fn remote(id: u32, extended: bool, len: u8) -> Option<Self> {
        let mut f = Self::with_id(id, extended, &[])?;
        if len > 8 {
            return None;
        }
        f.rtr = true;
        f.len = len;
        Some(f)
    }

    /// Identifier (11 or 29 bits).
    pub fn id(&self) -> u32 {
        self.id
    }
    /// Whether the identifier is 29-bit.
    pub fn is_extended(&self) -> bool {
        self.extended
    }
    /// Whether this is a remote frame.
    pub fn is_remote(&self) -> bool {
        self.rtr
    }
    /// Data length code (0..=8).
    pub fn len(&self) -> usize {
        self.len as usize
    }
    /// Whether the frame carries no data.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// The data bytes (empty for a remote frame).
    pub fn data(&self) -> &[u8] {
        if self.rtr {
            &[]
        } else {
            &self.data[..self.len as usize]
        }
    }
}

impl fmt::Debug for CanFrame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(self, f)
    }
}

impl fmt::Display for CanFrame {
    /// candump style: `181#0102030405060708`, `1ABCDEF0#..`, `181#R2`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.extended {
            write!(f, "{:08X}#", self.id)?;
        } else {
            write!(f, "{:03X}#", self.id)?;
        }
        if self.rtr {
            return write!(f, "R{}", self.len);
        }
        for b in self.data() {
            write!(f, "{b:02X}")?;
        }
        Ok(())
    }
}

/// Why a transport failed.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum CanError {
    /// The operating system refused (socket errors), with its message.
    #[error("CAN transport I/O error: {0}")]
    Io(String),
    /// The bus or peer is gone.
    #[error("CAN transport closed")]
    Closed,
    /// This endpoint fell behind and `0` frames were lost.
    #[error("CAN receiver overrun: {0} frames lost")]
    Lagged(u64),
    /// A datagram or frame that does not decode, with what was wrong.
    #[error("malformed CAN datagram: {0}")]
    Malformed(String),
}

impl CanError {
    /// Whether the transport still works after this error and `recv`/`send` may simply be
    /// called again: a receiver overrun, or one malformed datagram from a peer (dropped).
    pub fn is_transient(&self) -> bool {
        matches!(self, CanError::Lagged(_) | CanError::Malformed(_))
    }
}

/// A carrier of CAN frames.
pub trait CanTransport: Send + Sync + 'static {
    /// Send one frame.
    fn send(&self, frame: &CanFrame) -> impl Future<Output = Result<(), CanError>> + Send;
    /// The next frame from another node (frames this endpoint sent are not returned).
    /// Cancel-safe.
    fn recv(&self) -> impl Future<Output = Result<CanFrame, CanError>> + Send;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_limits_and_debug() {
        assert!(CanFrame::new(0x800, &[]).is_none());
        assert!(CanFrame::new(0x7FF, &[0; 9]).is_none());
        let f = CanFrame::new(0x181, &[1, 2, 0xAB]).unwrap();
        assert_eq!(format!("{f:?}"), "181#0102AB");
        assert_eq!(f.data(), &[1, 2, 0xAB]);
        let r = CanFrame::remote(0x701, false, 1).unwrap();
        assert_eq!(format!("{r:?}"), "701#R1");
        assert!(r.data().is_empty());
        let e = CanFrame::new_extended(0x1ABC_DEF0, &[0xFF]).unwrap();
        assert_eq!(format!("{e:?}"), "1ABCDEF0#FF");
    }

    #[test]
    fn transient_errors() {
        assert!(CanError::Lagged(3).is_transient());
        assert!(CanError::Malformed("x".into()).is_transient());
        assert!(!CanError::Closed.is_transient());
        assert!(!CanError::Io("x".into()).is_transient());
    }
}
