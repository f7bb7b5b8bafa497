//! SDO client (CiA 301 §7.2.4): expedited and segmented upload (read) and download (write).
//!
//! Built on canopen-rs 0.6.1's frame codecs (`canopen_rs::sdo::encode_*` / `decode_*`), with
//! what its `SdoClient` lacks (DESIGN §10) added here:
//! - a timeout on every exchange (each wait for a server response), after which an abort
//!   frame with 0x0504_0000 is sent;
//! - a check that an initiate response names the requested index and sub-index (the
//!   multiplexer); a mismatch aborts the transfer with an abort frame;
//! - abort frames on every local abort (cancel, protocol error, toggle error, timeout);
//! - segmented transfers of any length (canopen-rs stops at 32 bytes), bounded by a
//!   configurable maximum, with the toggle bit checked on every segment;
//! - abort codes decoded to the CiA 301 texts.
//!
//! Frame layout (CiA 301 §7.2.4.3), 8 data bytes, little-endian:
//!
//! | byte | initiate frames | segment frames |
//! |---|---|---|
//! | 0 | command: ccs/scs (bits 7–5), n (3–2), e (1), s (0) | command: cs (7–5), t (4), n (3–1), c (0) |
//! | 1–2 | index | data |
//! | 3 | sub-index | data |
//! | 4–7 | data (expedited) or size (segmented) | data |
//!
//! The client is sans-I/O: start a transfer with [`SdoClient::upload`] or
//! [`SdoClient::download`], feed frames and deadlines, poll frames to send and the outcome.

use super::{cob, frame};
use crate::can::CanFrame;
use canopen_rs::sdo as codec;
use canopen_rs::{Address, ByteString, NodeId, Value};
use std::collections::VecDeque;
use std::fmt;
use std::time::{Duration, Instant};
use thiserror::Error;

/// An object dictionary address: index and sub-index (the SDO "multiplexer").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ObjAddr {
    pub index: u16,
    pub sub: u8,
}

impl ObjAddr {
    pub const fn new(index: u16, sub: u8) -> Self {
        ObjAddr { index, sub }
    }

    fn address(self) -> Address {
        Address::new(self.index, self.sub)
    }

    /// The multiplexer of an 8-byte SDO initiate or abort frame (bytes 1–3).
    pub fn from_frame(p: &[u8; 8]) -> Self {
        ObjAddr::new(u16::from_le_bytes([p[1], p[2]]), p[3])
    }
}

impl fmt::Display for ObjAddr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "0x{:04X}:{:02X}", self.index, self.sub)
    }
}

/// An SDO abort code (CiA 301 §7.2.4.3.17), sent little-endian in bytes 4–7 of an abort frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct AbortCode(pub u32);

impl AbortCode {
    pub const TOGGLE_NOT_ALTERNATED: AbortCode = AbortCode(0x0503_0000);
    pub const TIMED_OUT: AbortCode = AbortCode(0x0504_0000);
    pub const COMMAND_INVALID: AbortCode = AbortCode(0x0504_0001);
    pub const OUT_OF_MEMORY: AbortCode = AbortCode(0x0504_0005);
    pub const UNSUPPORTED_ACCESS: AbortCode = AbortCode(0x0601_0000);
    pub const READ_OF_WRITE_ONLY: AbortCode = AbortCode(0x0601_0001);
    pub const WRITE_OF_READ_ONLY: AbortCode = AbortCode(0x0601_0002);
    pub const NO_OBJECT: AbortCode = AbortCode(0x0602_0000);
    pub const NOT_MAPPABLE: AbortCode = AbortCode(0x0604_0041);
    pub const PDO_TOO_LONG: AbortCode = AbortCode(0x0604_0042);
    pub const PARAMETER_INCOMPATIBLE: AbortCode = AbortCode(0x0604_0043);
    pub const HARDWARE_ERROR: AbortCode = AbortCode(0x0606_0000);
    pub const LENGTH_MISMATCH: AbortCode = AbortCode(0x0607_0010);
    pub const LENGTH_TOO_HIGH: AbortCode = AbortCode(0x0607_0012);
    pub const LENGTH_TOO_LOW: AbortCode = AbortCode(0x0607_0013);
    pub const NO_SUBINDEX: AbortCode = AbortCode(0x0609_0011);
    pub const INVALID_VALUE: AbortCode = AbortCode(0x0609_0030);
    pub const VALUE_TOO_HIGH: AbortCode = AbortCode(0x0609_0031);
    pub const VALUE_TOO_LOW: AbortCode = AbortCode(0x0609_0032);
    pub const GENERAL: AbortCode = AbortCode(0x0800_0000);
    pub const LOCAL_CONTROL: AbortCode = AbortCode(0x0800_0021);
    pub const DEVICE_STATE: AbortCode = AbortCode(0x0800_0022);

    /// The CiA 301 text of this code ("unknown abort code" for codes the standard does not
    /// list; those are usually manufacturer-specific).
    pub fn text(self) -> &'static str {
        match self.0 {
            0x0503_0000 => "toggle bit not alternated",
            0x0504_0000 => "SDO protocol timed out",
            0x0504_0001 => "client/server command specifier not valid or unknown",
            0x0504_0002 => "invalid block size (block mode only)",
            0x0504_0003 => "invalid sequence number (block mode only)",
            0x0504_0004 => "CRC error (block mode only)",
            0x0504_0005 => "out of memory",
            0x0601_0000 => "unsupported access to an object",
            0x0601_0001 => "attempt to read a write only object",
            0x0601_0002 => "attempt to write a read only object",
            0x0602_0000 => "object does not exist in the object dictionary",
            0x0604_0041 => "object cannot be mapped to the PDO",
            0x0604_0042 => {
                "the number and length of the objects to be mapped would exceed PDO length"
            }
            0x0604_0043 => "general parameter incompatibility reason",
            0x0604_0047 => "general internal incompatibility in the device",
            0x0606_0000 => "access failed due to a hardware error",
            0x0607_0010 => "data type does not match, length of service parameter does not match",
            0x0607_0012 => "data type does not match, length of service parameter too high",
            0x0607_0013 => "data type does not match, length of service parameter too low",
            0x0609_0011 => "sub-index does not exist",
            0x0609_0030 => "invalid value for parameter (download only)",
            0x0609_0031 => "value of parameter written too high (download only)",
            0x0609_0032 => "value of parameter written too low (download only)",
            0x0609_0036 => "maximum value is less than minimum value",
            0x060A_0023 => "resource not available: SDO connection",
            0x0800_0000 => "general error",
            0x0800_0020 => "data cannot be transferred or stored to the application",
            0x0800_0021 => {
                "data cannot be transferred or stored to the application because of local control"
            }
            0x0800_0022 => {
                "data cannot be transferred or stored to the application because of the present device state"
            }
            0x0800_0023 => {
                "object dictionary dynamic generation fails or no object dictionary is present"
            }
            0x0800_0024 => "no data available",
            _ => "unknown abort code",
        }
    }
}

impl fmt::Display for AbortCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "0x{:08X} ({})", self.0, self.text())
    }
}

/// Which way a transfer moves data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// Upload: the client reads from the server.
    Upload,
    /// Download: the client writes to the server.
    Download,
}

impl fmt::Display for Direction {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Direction::Upload => "read",
            Direction::Download => "write",
        })
    }
}

/// Why a transfer failed. Every variant names the object; those ending a transfer locally
/// name the abort code this client sent.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum SdoError {
    #[error("SDO {dir} of {obj}: the drive aborted with {code}")]
    Aborted {
        dir: Direction,
        obj: ObjAddr,
        code: AbortCode,
    },
    #[error("SDO {dir} of {obj}: no response within {} (sent abort {code})", crate::util::time::span(*timeout))]
    Timeout {
        dir: Direction,
        obj: ObjAddr,
        timeout: Duration,
        code: AbortCode,
    },
    #[error("SDO {dir} of {obj}: the response names object {got} (sent abort {code})")]
    WrongObject {
        dir: Direction,
        obj: ObjAddr,
        got: ObjAddr,
        code: AbortCode,
    },
    #[error("SDO {dir} of {obj}: {what} (sent abort {code})")]
    Protocol {
        dir: Direction,
        obj: ObjAddr,
        what: String,
        code: AbortCode,
    },
    #[error("SDO {dir} of {obj}: cancelled (sent abort {code})")]
    Cancelled {
        dir: Direction,
        obj: ObjAddr,
        code: AbortCode,
    },
    #[error("SDO {dir} of {obj}: {len} bytes exceed this client's limit of {max} bytes")]
    TooLarge {
        dir: Direction,
        obj: ObjAddr,
        len: usize,
        max: usize,
    },
    #[error("SDO client busy with {busy}: cannot start a transfer of {obj}")]
    Busy { obj: ObjAddr, busy: ObjAddr },
}

impl SdoError {
    /// The object the failed transfer addressed.
    pub fn object(&self) -> ObjAddr {
        match self {
            SdoError::Aborted { obj, .. }
            | SdoError::Timeout { obj, .. }
            | SdoError::WrongObject { obj, .. }
            | SdoError::Protocol { obj, .. }
            | SdoError::Cancelled { obj, .. }
            | SdoError::TooLarge { obj, .. }
            | SdoError::Busy { obj, .. } => *obj,
        }
    }

    /// The abort code on the wire: the drive's, or the one this client sent.
    pub fn abort_code(&self) -> Option<AbortCode> {
        match self {
            SdoError::Aborted { code, .. }
            | SdoError::Timeout { code, .. }
            | SdoError::WrongObject { code, .. }
            | SdoError::Protocol { code, .. }
            | SdoError::Cancelled { code, .. } => Some(*code),
            SdoError::TooLarge { .. } | SdoError::Busy { .. } => None,
        }
    }

    /// Whether the drive aborted because the object or sub-index does not exist.
    pub fn is_missing_object(&self) -> bool {
        matches!(
            self,
            SdoError::Aborted { code, .. }
                if *code == AbortCode::NO_OBJECT || *code == AbortCode::NO_SUBINDEX
        )
    }
}

/// A finished transfer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SdoOutcome {
    Uploaded { obj: ObjAddr, data: Vec<u8> },
    Downloaded { obj: ObjAddr },
}

#[derive(Debug)]
enum Phase {
    /// Upload initiate sent; waiting for its response.
    UploadInit,
    /// Segment request with `toggle` sent; waiting for the segment.
    UploadSeg {
        toggle: bool,
        size: Option<usize>,
        buf: Vec<u8>,
    },
    /// Download initiate sent (expedited when the data is 1..=4 bytes).
    DownloadInit { data: Vec<u8>, expedited: bool },
    /// Segment ending at `pos` with `toggle` sent; waiting for its acknowledgement.
    DownloadSeg {
        data: Vec<u8>,
        pos: usize,
        toggle: bool,
    },
}

#[derive(Debug)]
struct Transfer {
    obj: ObjAddr,
    dir: Direction,
    phase: Phase,
    deadline: Instant,
}

// Command specifiers (byte 0, bits 7–5) of server responses.
const SCS_UPLOAD_SEGMENT: u8 = 0;
const SCS_DOWNLOAD_SEGMENT: u8 = 1;
const SCS_UPLOAD_INITIATE: u8 = 2;
const SCS_DOWNLOAD_INITIATE: u8 = 3;
const CS_ABORT: u8 = 4;

/// The 8 bytes of an abort frame for `obj` with `code`: 0x80, index, sub-index, code.
pub fn encode_abort(obj: ObjAddr, code: AbortCode) -> [u8; 8] {
    let mut p = [0u8; 8];
    p[0] = 0x80;
    p[1..3].copy_from_slice(&obj.index.to_le_bytes());
    p[3] = obj.sub;
    p[4..8].copy_from_slice(&code.0.to_le_bytes());
    p
}

/// The SDO client for one server node.
#[derive(Debug)]
pub struct SdoClient {
    node: NodeId,
    timeout: Duration,
    max_len: usize,
    transfer: Option<Transfer>,
    tx: VecDeque<CanFrame>,
    outcomes: VecDeque<Result<SdoOutcome, SdoError>>,
}

impl SdoClient {
    /// Default bound on the length of one transfer.
    pub const DEFAULT_MAX_LEN: usize = 64 * 1024;

    /// A client for `node` waiting at most `timeout` for each response.
    pub fn new(node: NodeId, timeout: Duration) -> Self {
        SdoClient {
            node,
            timeout,
            max_len: Self::DEFAULT_MAX_LEN,
            transfer: None,
            tx: VecDeque::new(),
            outcomes: VecDeque::new(),
        }
    }

    /// Bound the length of one transfer (an upload announcing more is aborted with
    /// 0x0504_0005 "out of memory").
    pub fn with_max_len(mut self, max_len: usize) -> Self {
        self.max_len = max_len;
        self
    }

    /// The per-exchange timeout.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    fn request_id(&self) -> u16 {
        cob::SDO_RX + self.node.raw() as u16
    }

    fn response_id(&self) -> u16 {
        cob::SDO_TX + self.node.raw() as u16
    }

    /// Whether a transfer is in progress.
    pub fn is_busy(&self) -> bool {
        self.transfer.is_some()
    }

    /// The object of the transfer in progress.
    pub fn current(&self) -> Option<ObjAddr> {
        self.transfer.as_ref().map(|t| t.obj)
    }

    fn check_idle(&self, obj: ObjAddr) -> Result<(), SdoError> {
        match &self.transfer {
            Some(t) => Err(SdoError::Busy { obj, busy: t.obj }),
            None => Ok(()),
        }
    }

    fn send(&mut self, p: [u8; 8]) {
        self.tx.push_back(frame(self.request_id(), &p));
    }

    /// Start reading `obj`.
    pub fn upload(&mut self, obj: ObjAddr, now: Instant) -> Result<(), SdoError> {
        self.check_idle(obj)?;
        // Initiate upload request: 0x40, index, sub-index, 4 reserved bytes.
        self.send(codec::encode_upload_request(obj.address()));
        self.transfer = Some(Transfer {
            obj,
            dir: Direction::Upload,
            phase: Phase::UploadInit,
            deadline: now + self.timeout,
        });
        Ok(())
    }

    /// Start writing `data` to `obj`: expedited for 1..=4 bytes, segmented otherwise.
    pub fn download(&mut self, obj: ObjAddr, data: Vec<u8>, now: Instant) -> Result<(), SdoError> {
        self.check_idle(obj)?;
        let dir = Direction::Download;
        if data.len() > self.max_len {
            return Err(SdoError::TooLarge {
                dir,
                obj,
                len: data.len(),
                max: self.max_len,
            });
        }
        let expedited = (1..=4).contains(&data.len());
        let p = if expedited {
            // Expedited: 0x23/0x27/0x2B/0x2F (n = 4 − len unused bytes), data in bytes 4–7.
            let value = ByteString::from_bytes(&data).map(Value::OctetString);
            match value.and_then(|v| codec::encode_download_expedited(obj.address(), &v)) {
                Ok(p) => p,
                Err(e) => {
                    return Err(SdoError::Protocol {
                        dir,
                        obj,
                        what: format!("cannot encode {} bytes expedited: {e}", data.len()),
                        code: AbortCode::GENERAL,
                    });
                }
            }
        } else {
            // Segmented initiate: 0x21 (size indicated), size in bytes 4–7.
            codec::encode_download_initiate_segmented(obj.address(), data.len() as u32)
        };
        self.send(p);
        self.transfer = Some(Transfer {
            obj,
            dir,
            phase: Phase::DownloadInit { data, expedited },
            deadline: now + self.timeout,
        });
        Ok(())
    }

    /// Abort the transfer in progress locally (sends an abort frame with `code`); its outcome
    /// is `SdoError::Cancelled`. Returns whether there was one.
    pub fn cancel(&mut self, code: AbortCode) -> bool {
        match self.transfer.take() {
            Some(t) => {
                self.send(encode_abort(t.obj, code));
                self.outcomes.push_back(Err(SdoError::Cancelled {
                    dir: t.dir,
                    obj: t.obj,
                    code,
                }));
                true
            }
            None => false,
        }
    }

    /// End the transfer locally: abort frame with `code`, then the error.
    fn fail(&mut self, t: &Transfer, code: AbortCode, err: SdoError) {
        self.send(encode_abort(t.obj, code));
        self.outcomes.push_back(Err(err));
    }

    /// Feed a received frame. Returns whether it was this client's (the server's response
    /// COB-ID); responses arriving with no transfer in progress are dropped.
    pub fn handle_frame(&mut self, f: &CanFrame, now: Instant) -> bool {
        if f.is_extended() || f.is_remote() || f.id() != self.response_id() as u32 {
            return false;
        }
        let Some(t) = self.transfer.take() else {
            return true;
        };
        // CiA 301 SDO frames have 8 data bytes; shorter ones are padded with zeros.
        let mut p = [0u8; 8];
        p[..f.len()].copy_from_slice(f.data());
        if f.is_empty() {
            let err = self.protocol(&t, "empty SDO response".into(), AbortCode::COMMAND_INVALID);
            self.fail(&t, AbortCode::COMMAND_INVALID, err);
            return true;
        }
        let cs = p[0] >> 5;
        if cs == CS_ABORT {
            // The abort ends this transfer whichever object it names (some servers abort
            // with a zero multiplexer); the error names the object we asked for.
            let code = match codec::decode_abort(&p) {
                Ok((_, c)) => c,
                Err(_) => u32::from_le_bytes([p[4], p[5], p[6], p[7]]),
            };
            self.outcomes.push_back(Err(SdoError::Aborted {
                dir: t.dir,
                obj: t.obj,
                code: AbortCode(code),
            }));
            return true;
        }
        self.advance(t, cs, &p, now);
        true
    }

    fn protocol(&self, t: &Transfer, what: String, code: AbortCode) -> SdoError {
        SdoError::Protocol {
            dir: t.dir,
            obj: t.obj,
            what,
            code,
        }
    }

    fn wrong_cs(&mut self, t: Transfer, cs: u8, want: &str) {
        let code = AbortCode::COMMAND_INVALID;
        let err = self.protocol(
            &t,
            format!("unexpected server command specifier {cs} (wanted {want})"),
            code,
        );
        self.fail(&t, code, err);
    }

    /// The initiate response must name the requested object, else abort.
    fn check_mux(&mut self, t: &Transfer, p: &[u8; 8]) -> bool {
        let got = ObjAddr::from_frame(p);
        if got == t.obj {
            return true;
        }
        let code = AbortCode::GENERAL;
        let err = SdoError::WrongObject {
            dir: t.dir,
            obj: t.obj,
            got,
            code,
        };
        self.fail(t, code, err);
        false
    }

    fn advance(&mut self, mut t: Transfer, cs: u8, p: &[u8; 8], now: Instant) {
        let phase = std::mem::replace(&mut t.phase, Phase::UploadInit);
        match phase {
            Phase::UploadInit => {
                if cs != SCS_UPLOAD_INITIATE {
                    return self.wrong_cs(t, cs, "2, initiate upload response");
                }
                if !self.check_mux(&t, p) {
                    return;
                }
                let expedited = p[0] & 0x02 != 0;
                let sized = p[0] & 0x01 != 0;
                if expedited {
                    // e = 1: the data is in bytes 4–7; with s = 1, n (bits 3–2) unused bytes.
                    let len = if sized {
                        4 - ((p[0] >> 2) & 0x03) as usize
                    } else {
                        4
                    };
                    self.outcomes.push_back(Ok(SdoOutcome::Uploaded {
                        obj: t.obj,
                        data: p[4..4 + len].to_vec(),
                    }));
                    return;
                }
                // e = 0: segmented; with s = 1 bytes 4–7 hold the size.
                let size = sized.then(|| u32::from_le_bytes([p[4], p[5], p[6], p[7]]) as usize);
                if let Some(n) = size.filter(|&n| n > self.max_len) {
                    let err = SdoError::TooLarge {
                        dir: t.dir,
                        obj: t.obj,
                        len: n,
                        max: self.max_len,
                    };
                    return self.fail(&t, AbortCode::OUT_OF_MEMORY, err);
                }
                // Upload segment request: 0x60 | t, 7 reserved bytes.
                self.send(codec::encode_upload_segment_request(false));
                t.phase = Phase::UploadSeg {
                    toggle: false,
                    size,
                    buf: Vec::with_capacity(size.unwrap_or(0)),
                };
            }
            Phase::UploadSeg {
                toggle,
                size,
                mut buf,
            } => {
                if cs != SCS_UPLOAD_SEGMENT {
                    return self.wrong_cs(t, cs, "0, upload segment response");
                }
                let seg = match codec::decode_data_segment(p) {
                    Ok(s) => s,
                    Err(e) => {
                        let code = AbortCode::COMMAND_INVALID;
                        let err = self.protocol(&t, format!("bad upload segment: {e}"), code);
                        return self.fail(&t, code, err);
                    }
                };
                if seg.toggle != toggle {
                    let code = AbortCode::TOGGLE_NOT_ALTERNATED;
                    let err = self.protocol(
                        &t,
                        format!(
                            "upload segment toggle {} where {} was due",
                            seg.toggle as u8, toggle as u8
                        ),
                        code,
                    );
                    return self.fail(&t, code, err);
                }
                buf.extend_from_slice(seg.data);
                if buf.len() > self.max_len || size.is_some_and(|n| buf.len() > n) {
                    let code = AbortCode::LENGTH_TOO_HIGH;
                    let err = self.protocol(
                        &t,
                        format!(
                            "received {} bytes, more than the indicated {} / limit {}",
                            buf.len(),
                            size.map_or("-".into(), |n| n.to_string()),
                            self.max_len
                        ),
                        code,
                    );
                    return self.fail(&t, code, err);
                }
                if seg.last {
                    if let Some(n) = size.filter(|&n| n != buf.len()) {
                        let code = AbortCode::LENGTH_MISMATCH;
                        let err = self.protocol(
                            &t,
                            format!("received {} bytes, the server indicated {n}", buf.len()),
                            code,
                        );
                        return self.fail(&t, code, err);
                    }
                    self.outcomes.push_back(Ok(SdoOutcome::Uploaded {
                        obj: t.obj,
                        data: buf,
                    }));
                    return;
                }
                self.send(codec::encode_upload_segment_request(!toggle));
                t.phase = Phase::UploadSeg {
                    toggle: !toggle,
                    size,
                    buf,
                };
            }
            Phase::DownloadInit { data, expedited } => {
                if cs != SCS_DOWNLOAD_INITIATE {
                    return self.wrong_cs(t, cs, "3, initiate download response");
                }
                if !self.check_mux(&t, p) {
                    return;
                }
                if expedited {
                    self.outcomes
                        .push_back(Ok(SdoOutcome::Downloaded { obj: t.obj }));
                    return;
                }
                let pos = self.send_segment(&data, 0, false);
                t.phase = Phase::DownloadSeg {
                    data,
                    pos,
                    toggle: false,
                };
            }
            Phase::DownloadSeg { data, pos, toggle } => {
                if cs != SCS_DOWNLOAD_SEGMENT {
                    return self.wrong_cs(t, cs, "1, download segment response");
                }
                let got = p[0] & 0x10 != 0;
                if got != toggle {
                    let code = AbortCode::TOGGLE_NOT_ALTERNATED;
                    let err = self.protocol(
                        &t,
                        format!(
                            "download segment acknowledged with toggle {} where {} was sent",
                            got as u8, toggle as u8
                        ),
                        code,
                    );
                    return self.fail(&t, code, err);
                }
                if pos >= data.len() {
                    self.outcomes
                        .push_back(Ok(SdoOutcome::Downloaded { obj: t.obj }));
                    return;
                }
                let next = self.send_segment(&data, pos, !toggle);
                t.phase = Phase::DownloadSeg {
                    data,
                    pos: next,
                    toggle: !toggle,
                };
            }
        }
        t.deadline = now + self.timeout;
        self.transfer = Some(t);
    }

    /// Send the download segment starting at `pos`; returns where the next one starts.
    fn send_segment(&mut self, data: &[u8], pos: usize, toggle: bool) -> usize {
        let end = (pos + codec::SEGMENT_DATA_MAX).min(data.len());
        let last = end == data.len();
        // Segment: cs 000, t (bit 4), n = 7 − len unused bytes (bits 3–1), c = last (bit 0).
        match codec::encode_data_segment(&data[pos..end], toggle, last) {
            Ok(p) => self.send(p),
            Err(_) => unreachable!("a segment carries at most 7 bytes"),
        }
        end
    }

    /// Feed the clock: a transfer whose response is overdue is aborted (0x0504_0000).
    pub fn handle_timeout(&mut self, now: Instant) {
        if let Some(t) = self.transfer.take() {
            if now >= t.deadline {
                let code = AbortCode::TIMED_OUT;
                let err = SdoError::Timeout {
                    dir: t.dir,
                    obj: t.obj,
                    timeout: self.timeout,
                    code,
                };
                self.fail(&t, code, err);
            } else {
                self.transfer = Some(t);
            }
        }
    }

    /// When `handle_timeout` must next be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.transfer.as_ref().map(|t| t.deadline)
    }

    /// The next frame to send.
    pub fn poll_transmit(&mut self) -> Option<CanFrame> {
        self.tx.pop_front()
    }

    /// The next finished transfer.
    pub fn poll_outcome(&mut self) -> Option<Result<SdoOutcome, SdoError>> {
        self.outcomes.pop_front()
    }
}

/// Little-endian value helpers for the fixed-size CANopen types used by the drive profile.
pub mod value {
    /// `n` bytes interpreted as an unsigned little-endian integer (`None` if the length is not
    /// `n`).
    pub fn uint(data: &[u8], n: usize) -> Option<u64> {
        (data.len() == n && n <= 8).then(|| {
            data.iter()
                .rev()
                .fold(0u64, |acc, &b| (acc << 8) | b as u64)
        })
    }
    pub fn u8(data: &[u8]) -> Option<u8> {
        uint(data, 1).map(|v| v as u8)
    }
    pub fn i8(data: &[u8]) -> Option<i8> {
        uint(data, 1).map(|v| v as u8 as i8)
    }
    pub fn u16(data: &[u8]) -> Option<u16> {
        uint(data, 2).map(|v| v as u16)
    }
    pub fn u32(data: &[u8]) -> Option<u32> {
        uint(data, 4).map(|v| v as u32)
    }
    pub fn i32(data: &[u8]) -> Option<i32> {
        uint(data, 4).map(|v| v as u32 as i32)
    }
}

#[cfg(test)]
mod tests {
    //! Byte-level tests. The reference traces are python-canopen 2.4.1's own frames (its
    //! `SdoClient` against its `SdoServer` on a python-can virtual bus, node 1), recorded
    //! once and pasted here; the byte layouts are CiA 301 §7.2.4.3.
    use super::*;

    const TIMEOUT: Duration = Duration::from_millis(500);

    fn client() -> SdoClient {
        SdoClient::new(NodeId::new(1).unwrap(), TIMEOUT)
    }

    /// A frame from candump text, `581#4308100026000000`.
    fn parse(s: &str) -> CanFrame {
        let (id, data) = s.split_once('#').unwrap();
        let id = u16::from_str_radix(id, 16).unwrap();
        let bytes: Vec<u8> = (0..data.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&data[i..i + 2], 16).unwrap())
            .collect();
        CanFrame::new(id, &bytes).unwrap()
    }

    fn sent(c: &mut SdoClient) -> Vec<String> {
        std::iter::from_fn(|| c.poll_transmit())
            .map(|f| format!("{f:?}"))
            .collect()
    }

    /// Run a trace: lines starting 601 are what the client must send, 581 what the server
    /// answers.
    fn run(c: &mut SdoClient, trace: &[&str], t0: Instant) {
        let mut now = t0;
        for line in trace {
            now += Duration::from_millis(1);
            if line.starts_with("601#") {
                assert_eq!(sent(c), vec![line.to_string()]);
            } else {
                assert!(c.handle_frame(&parse(line), now));
            }
        }
        assert!(sent(c).is_empty());
    }

    #[test]
    fn expedited_upload_matches_python_canopen() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x6064, 0), t0).unwrap();
        // 0x40 = ccs 2 (initiate upload); 64 60 = index 0x6064 LE; 00 = sub; 4 reserved bytes.
        // 0x43 = scs 2, n = 0, e = 1, s = 1: four data bytes C7 CF FF FF = −12345 LE.
        run(
            &mut c,
            &["601#4064600000000000", "581#43646000C7CFFFFF"],
            t0,
        );
        let out = c.poll_outcome().unwrap().unwrap();
        let SdoOutcome::Uploaded { data, .. } = out else {
            panic!("{out:?}")
        };
        assert_eq!(value::i32(&data), Some(-12345));
        assert!(!c.is_busy());
    }

    #[test]
    fn expedited_download_matches_python_canopen() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.download(ObjAddr::new(0x6040, 0), vec![0x0F, 0x00], t0)
            .unwrap();
        // 0x2B = ccs 1 (initiate download), n = 2 unused (bits 3–2 = 10), e = 1, s = 1.
        // 0x60 = scs 3, the confirmation repeats the multiplexer.
        run(
            &mut c,
            &["601#2B4060000F000000", "581#6040600000000000"],
            t0,
        );
        assert_eq!(
            c.poll_outcome().unwrap().unwrap(),
            SdoOutcome::Downloaded {
                obj: ObjAddr::new(0x6040, 0)
            }
        );
        // 1, 3 and 4 bytes: command 0x2F, 0x27, 0x23.
        for (data, cmd) in [
            (vec![1u8], 0x2F),
            (vec![1, 2, 3], 0x27),
            (vec![1, 2, 3, 4], 0x23),
        ] {
            let mut c = client();
            c.download(ObjAddr::new(0x2000, 7), data.clone(), t0)
                .unwrap();
            let f = c.poll_transmit().unwrap();
            assert_eq!(f.data()[0], cmd);
            assert_eq!(&f.data()[1..4], &[0x00, 0x20, 0x07]);
            assert_eq!(&f.data()[4..4 + data.len()], &data[..]);
        }
    }

    /// A 38-byte VISIBLE_STRING (more than canopen-rs's 32-byte limit), six segments.
    #[test]
    fn segmented_upload_over_32_bytes_matches_python_canopen() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x1008, 0), t0).unwrap();
        run(
            &mut c,
            &[
                "601#4008100000000000",
                // 0x41 = scs 2, e = 0, s = 1: size 0x26 = 38 in bytes 4–7.
                "581#4108100026000000",
                // 0x60 = ccs 3 (upload segment), t = 0; then 0x70 with t = 1, alternating.
                "601#6000000000000000",
                // 0x00: scs 0, t = 0, n = 0 (7 bytes), c = 0.
                "581#0061786973636F6D",
                "601#7000000000000000",
                "581#107020666F6C6C6F",
                "601#6000000000000000",
                "581#0077657220647269",
                "601#7000000000000000",
                "581#1076652C20436941",
                "601#6000000000000000",
                "581#0020343032207477",
                "601#7000000000000000",
                // 0x19: t = 1, n = 4 unused (bits 3–1 = 100), c = 1 (last): 3 bytes.
                "581#19696E2100000000",
            ],
            t0,
        );
        let Ok(SdoOutcome::Uploaded { data, .. }) = c.poll_outcome().unwrap() else {
            panic!()
        };
        assert_eq!(data, b"axiscomp follower drive, CiA 402 twin!");
        assert_eq!(data.len(), 38);
    }

    /// 40 bytes written in six segments, byte-for-byte what python-canopen sends.
    #[test]
    fn segmented_download_over_32_bytes_matches_python_canopen() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        let data: Vec<u8> = (0x30..0x30 + 40).collect();
        c.download(ObjAddr::new(0x2000, 0), data, t0).unwrap();
        run(
            &mut c,
            &[
                // 0x21 = ccs 1, e = 0, s = 1: size 0x28 = 40 in bytes 4–7.
                "601#2100200028000000",
                "581#6000200000000000",
                // 0x00 = ccs 0, t = 0, n = 0, c = 0: seven data bytes.
                "601#0030313233343536",
                // 0x20 = scs 1, t = 0: the server echoes the toggle.
                "581#2000000000000000",
                "601#103738393A3B3C3D",
                "581#3000000000000000",
                "601#003E3F4041424344",
                "581#2000000000000000",
                "601#1045464748494A4B",
                "581#3000000000000000",
                "601#004C4D4E4F505152",
                "581#2000000000000000",
                // 0x15 = t = 1, n = 2 unused (bits 3–1 = 010), c = 1: five bytes 53..57.
                "601#1553545556570000",
                "581#3000000000000000",
            ],
            t0,
        );
        assert!(matches!(
            c.poll_outcome(),
            Some(Ok(SdoOutcome::Downloaded { .. }))
        ));
    }

    #[test]
    fn six_and_zero_byte_downloads_are_segmented() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.download(ObjAddr::new(0x2000, 0), b"ABCDEF".to_vec(), t0)
            .unwrap();
        run(
            &mut c,
            &[
                "601#2100200006000000",
                "581#6000200000000000",
                // 0x03: n = 1 unused, c = 1.
                "601#0341424344454600",
                "581#2000000000000000",
            ],
            t0,
        );
        assert!(matches!(c.poll_outcome(), Some(Ok(_))));
        // Zero bytes: size 0, then one empty last segment (n = 7, c = 1 → 0x0F).
        c.download(ObjAddr::new(0x2000, 0), vec![], t0).unwrap();
        run(
            &mut c,
            &[
                "601#2100200000000000",
                "581#6000200000000000",
                "601#0F00000000000000",
                "581#2000000000000000",
            ],
            t0,
        );
        assert!(matches!(c.poll_outcome(), Some(Ok(_))));
    }

    #[test]
    fn wrong_multiplexer_sends_abort() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x6064, 0), t0).unwrap();
        sent(&mut c);
        // The response names sub-index 1.
        c.handle_frame(&parse("581#43646001C7CFFFFF"), t0);
        // Abort: 0x80, the requested multiplexer, 0x08000000 (general error) LE.
        assert_eq!(sent(&mut c), vec!["601#8064600000000008"]);
        let err = c.poll_outcome().unwrap().unwrap_err();
        assert_eq!(
            err,
            SdoError::WrongObject {
                dir: Direction::Upload,
                obj: ObjAddr::new(0x6064, 0),
                got: ObjAddr::new(0x6064, 1),
                code: AbortCode::GENERAL
            }
        );
        assert!(err.to_string().contains("names object 0x6064:01"), "{err}");
        assert!(!c.is_busy());

        // Same on a download confirmation naming another index.
        c.download(ObjAddr::new(0x6040, 0), vec![6, 0], t0).unwrap();
        sent(&mut c);
        c.handle_frame(&parse("581#6041600000000000"), t0);
        assert_eq!(sent(&mut c), vec!["601#8040600000000008"]);
        assert!(matches!(
            c.poll_outcome(),
            Some(Err(SdoError::WrongObject { .. }))
        ));
    }

    #[test]
    fn timeout_sends_abort() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x1008, 0), t0).unwrap();
        sent(&mut c);
        assert_eq!(c.poll_timeout(), Some(t0 + TIMEOUT));
        c.handle_timeout(t0 + TIMEOUT - Duration::from_millis(1));
        assert!(sent(&mut c).is_empty() && c.is_busy());
        c.handle_timeout(t0 + TIMEOUT);
        // 0x05040000 "SDO protocol timed out", LE in bytes 4–7.
        assert_eq!(sent(&mut c), vec!["601#8008100000000405"]);
        let err = c.poll_outcome().unwrap().unwrap_err();
        assert!(matches!(err, SdoError::Timeout { .. }));
        assert!(err.to_string().contains("SDO protocol timed out"), "{err}");
        assert_eq!(c.poll_timeout(), None);
        // A late response is dropped.
        assert!(c.handle_frame(&parse("581#4108100026000000"), t0 + TIMEOUT * 2));
        assert!(c.poll_outcome().is_none() && sent(&mut c).is_empty());
    }

    /// The timeout applies per exchange: each response restarts it.
    #[test]
    fn timeout_restarts_on_each_segment() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x1008, 0), t0).unwrap();
        let t1 = t0 + Duration::from_millis(400);
        c.handle_frame(&parse("581#4108100026000000"), t1);
        assert_eq!(c.poll_timeout(), Some(t1 + TIMEOUT));
        c.handle_timeout(t0 + TIMEOUT);
        assert!(c.is_busy());
        // Mid-transfer timeout: the abort names the object too.
        c.handle_timeout(t1 + TIMEOUT);
        assert_eq!(sent(&mut c).last().unwrap(), "601#8008100000000405");
    }

    #[test]
    fn toggle_error_sends_abort() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x1008, 0), t0).unwrap();
        c.handle_frame(&parse("581#4108100026000000"), t0);
        sent(&mut c);
        // First segment must carry t = 0; the server sends t = 1.
        c.handle_frame(&parse("581#1061786973636F6D"), t0);
        assert_eq!(sent(&mut c), vec!["601#8008100000000305"]);
        assert!(matches!(
            c.poll_outcome(),
            Some(Err(SdoError::Protocol {
                code: AbortCode::TOGGLE_NOT_ALTERNATED,
                ..
            }))
        ));
        // Download: the acknowledgement must echo the segment's toggle.
        c.download(ObjAddr::new(0x2000, 0), vec![0; 10], t0)
            .unwrap();
        c.handle_frame(&parse("581#6000200000000000"), t0);
        sent(&mut c);
        c.handle_frame(&parse("581#3000000000000000"), t0);
        assert_eq!(sent(&mut c), vec!["601#8000200000000305"]);
    }

    #[test]
    fn server_abort_is_typed_with_text() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.download(ObjAddr::new(0x6099, 3), vec![1, 0, 0, 0], t0)
            .unwrap();
        sent(&mut c);
        c.handle_frame(&parse("581#8099600311000906"), t0);
        let err = c.poll_outcome().unwrap().unwrap_err();
        assert_eq!(err.abort_code(), Some(AbortCode::NO_SUBINDEX));
        assert!(err.is_missing_object());
        assert_eq!(err.object(), ObjAddr::new(0x6099, 3));
        assert_eq!(
            err.to_string(),
            "SDO write of 0x6099:03: the drive aborted with 0x06090011 (sub-index does not exist)"
        );
        // No abort is sent back for the server's abort.
        assert!(sent(&mut c).is_empty());
    }

    #[test]
    fn unexpected_command_and_length_errors() {
        let t0 = crate::util::clock::now();
        // A download confirmation to an upload: command specifier invalid.
        let mut c = client();
        c.upload(ObjAddr::new(0x6041, 0), t0).unwrap();
        sent(&mut c);
        c.handle_frame(&parse("581#6041600000000000"), t0);
        assert_eq!(sent(&mut c), vec!["601#8041600001000405"]);
        assert!(matches!(
            c.poll_outcome(),
            Some(Err(SdoError::Protocol {
                code: AbortCode::COMMAND_INVALID,
                ..
            }))
        ));
        // Expedited without size (e = 1, s = 0: 0x42): four bytes.
        c.upload(ObjAddr::new(0x6041, 0), t0).unwrap();
        c.handle_frame(&parse("581#4241600037020000"), t0);
        let Some(Ok(SdoOutcome::Uploaded { data, .. })) = c.poll_outcome() else {
            panic!()
        };
        assert_eq!(data, vec![0x37, 0x02, 0, 0]);
        // Segmented upload with fewer bytes than indicated.
        c.upload(ObjAddr::new(0x1008, 0), t0).unwrap();
        c.handle_frame(&parse("581#410810000A000000"), t0);
        c.handle_frame(&parse("581#0B41424300000000"), t0);
        assert!(sent(&mut c).last().unwrap().ends_with("10000706"));
        // Announced size above the limit: out of memory.
        let mut c = client().with_max_len(100);
        c.upload(ObjAddr::new(0x1008, 0), t0).unwrap();
        c.handle_frame(&parse("581#4108100000100000"), t0);
        assert_eq!(sent(&mut c).last().unwrap(), "601#8008100005000405");
        assert!(matches!(
            c.poll_outcome(),
            Some(Err(SdoError::TooLarge { len: 4096, .. }))
        ));
    }

    #[test]
    fn busy_cancel_and_foreign_frames() {
        let (t0, mut c) = (crate::util::clock::now(), client());
        c.upload(ObjAddr::new(0x6041, 0), t0).unwrap();
        assert!(matches!(
            c.upload(ObjAddr::new(0x6064, 0), t0),
            Err(SdoError::Busy { .. })
        ));
        // Frames of other nodes and services are not ours.
        assert!(!c.handle_frame(&parse("582#4341600037020000"), t0));
        assert!(!c.handle_frame(&parse("181#3702"), t0));
        sent(&mut c);
        assert!(c.cancel(AbortCode::LOCAL_CONTROL));
        assert_eq!(sent(&mut c), vec!["601#8041600021000008"]);
        assert!(matches!(
            c.poll_outcome(),
            Some(Err(SdoError::Cancelled { .. }))
        ));
        assert!(!c.cancel(AbortCode::GENERAL));
    }

    #[test]
    fn abort_code_texts() {
        assert_eq!(
            AbortCode(0x0602_0000).to_string(),
            "0x06020000 (object does not exist in the object dictionary)"
        );
        assert_eq!(
            AbortCode(0x0601_0002).text(),
            "attempt to write a read only object"
        );
        assert_eq!(
            AbortCode(0x0604_0042).text(),
            "the number and length of the objects to be mapped would exceed PDO length"
        );
        assert_eq!(AbortCode(0x1234_5678).text(), "unknown abort code");
        // Our abort frames equal canopen-rs's for the codes it knows.
        assert_eq!(
            encode_abort(ObjAddr::new(0x2000, 1), AbortCode::NO_OBJECT),
            codec::encode_abort(
                Address::new(0x2000, 1),
                codec::SdoAbortCode::ObjectDoesNotExist
            )
        );
    }
}
