//! Modbus TCP (DESIGN §6, §10), over tokio-modbus 0.17 with the guards it lacks.
//!
//! - `codec`: register codecs (u16, i16, u32, i32, f32 in the four word/byte orders) and
//!   validated address ranges (1..=125 registers per read, 1..=123 per write).
//! - `link`: the client link, a task owning the TCP connection behind a cloneable handle, with
//!   a per-call timeout, TCP_NODELAY, drop-and-reconnect with backoff after any transport error,
//!   timeout or malformed reply (a timed-out call otherwise leaves the next reply off by one),
//!   its state on a `watch` and its statistics.
//! - `paced`: the acquisition's block read at a fixed rate, sent at one tick and collected at
//!   the next from a socket off the reactor (one wake-up per frame), with the link's guards.
//! - `pipelined`: the acquisition's block read unthrottled, several requests in flight on one
//!   connection (matched by transaction id), nothing allocated per frame, with the link's guards.
//! - `server`: scaffolding for our own servers (the twin's I/O module, later a PLC twin and the
//!   pull server): a register bank, request validation done by us (never trusting the library),
//!   Modbus exceptions instead of dropped connections, a peer allow-list and fault injection.
//!
//! rodbus is not used (its licence forbids it); its channel/handle design is followed.

pub mod codec;
pub mod link;
pub mod paced;
pub mod pipelined;
pub mod server;

pub use codec::{AddressError, ReadRange, ValueType, WordOrder, WriteRange};
pub use link::{Link, LinkConfig, LinkError, LinkState, LinkStats, Monitor};
pub use paced::PacedReader;
pub use pipelined::PipelinedReader;
pub use server::{MemoryBank, RegisterBank, ServerConfig, ServerError, ServerHandle};

use serde::Deserialize;
use std::fmt;

/// Which register table a block lives in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RegisterKind {
    /// Input registers (read-only, function 4; "3x" in 1-based notation).
    Input,
    /// Holding registers (function 3 to read, 6 and 16 to write; "4x").
    Holding,
}

impl fmt::Display for RegisterKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            RegisterKind::Input => "input",
            RegisterKind::Holding => "holding",
        })
    }
}

/// A Modbus exception code (Modbus Application Protocol v1.1b3, §7), copyable and named.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Exception {
    IllegalFunction,
    IllegalDataAddress,
    IllegalDataValue,
    ServerDeviceFailure,
    Acknowledge,
    ServerDeviceBusy,
    MemoryParityError,
    GatewayPathUnavailable,
    GatewayTargetDevice,
    /// A code the specification does not name.
    Other(u8),
}

impl Exception {
    /// The code on the wire.
    pub fn code(self) -> u8 {
        match self {
            Exception::IllegalFunction => 0x01,
            Exception::IllegalDataAddress => 0x02,
            Exception::IllegalDataValue => 0x03,
            Exception::ServerDeviceFailure => 0x04,
            Exception::Acknowledge => 0x05,
            Exception::ServerDeviceBusy => 0x06,
            Exception::MemoryParityError => 0x08,
            Exception::GatewayPathUnavailable => 0x0A,
            Exception::GatewayTargetDevice => 0x0B,
            Exception::Other(c) => c,
        }
    }

    /// The exception for a code.
    pub fn from_code(code: u8) -> Self {
        match code {
            0x01 => Exception::IllegalFunction,
            0x02 => Exception::IllegalDataAddress,
            0x03 => Exception::IllegalDataValue,
            0x04 => Exception::ServerDeviceFailure,
            0x05 => Exception::Acknowledge,
            0x06 => Exception::ServerDeviceBusy,
            0x08 => Exception::MemoryParityError,
            0x0A => Exception::GatewayPathUnavailable,
            0x0B => Exception::GatewayTargetDevice,
            c => Exception::Other(c),
        }
    }

    /// The specification's name.
    pub fn name(self) -> &'static str {
        match self {
            Exception::IllegalFunction => "illegal function",
            Exception::IllegalDataAddress => "illegal data address",
            Exception::IllegalDataValue => "illegal data value",
            Exception::ServerDeviceFailure => "server device failure",
            Exception::Acknowledge => "acknowledge",
            Exception::ServerDeviceBusy => "server device busy",
            Exception::MemoryParityError => "memory parity error",
            Exception::GatewayPathUnavailable => "gateway path unavailable",
            Exception::GatewayTargetDevice => "gateway target device failed to respond",
            Exception::Other(_) => "unknown exception",
        }
    }
}

impl fmt::Display for Exception {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "exception 0x{:02X} ({})", self.code(), self.name())
    }
}

impl From<tokio_modbus::ExceptionCode> for Exception {
    fn from(e: tokio_modbus::ExceptionCode) -> Self {
        Exception::from_code(u8::from(e))
    }
}

impl From<Exception> for tokio_modbus::ExceptionCode {
    fn from(e: Exception) -> Self {
        tokio_modbus::ExceptionCode::new(e.code())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exception_codes_round_trip_with_names() {
        for code in 0u8..=0x0C {
            let e = Exception::from_code(code);
            assert_eq!(e.code(), code);
            let lib: tokio_modbus::ExceptionCode = e.into();
            assert_eq!(Exception::from(lib), e);
        }
        assert_eq!(
            Exception::IllegalDataAddress.to_string(),
            "exception 0x02 (illegal data address)"
        );
        assert_eq!(Exception::from_code(0x07), Exception::Other(7));
    }
}
