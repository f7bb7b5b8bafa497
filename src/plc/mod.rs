//! Compensation tables to the CNC's PLC over Modbus TCP (DESIGN §6): the plc-map schema, the
//! table block codec, the push handshake and the pull server. The protocol itself (fields,
//! codes, CRC, sign, the two handshakes) is specified in `plc-maps/README.md`.
//!
//! - `map`: CNC maps (`plc-maps/cnc/*.toml`), raw then validated; documentation numbering.
//! - `table`: a table as header + payload registers and back (word orders, resolution,
//!   rounding, limits, CRC-32/ISO-HDLC), and the PLC side's validation with rejection codes.
//! - `publish`: push — a sans-I/O handshake machine (`handle_reply`/`handle_timeout(now)`,
//!   `poll_transmit`, `poll_event`) and a thin async driver over `modbus::Link`.
//! - `serve`: pull — our Modbus server holding the last approved table read-only, the
//!   published sequence, and one writable acknowledgement range for the PLC.
//!
//! The twin's PLC, which plays the other side of both, is `sim::plc`.

pub mod check;
pub mod map;
pub mod publish;
pub mod serve;
pub mod table;

pub use map::{CncMap, MapError};
pub use publish::{PublishError, PublishOutcome, Publisher, Timeouts, publish};
pub use serve::{PullAck, PullConfig, PullError, PullServer};
pub use table::{Encoded, PlcTable, Reject, RejectCode, TableDirection, TableError, encode};

use crate::modbus::codec::{self, ReadRange};
use crate::modbus::{Link, LinkError, RegisterKind};
use crate::store::PublicationOutcome;
use map::Field;
use std::collections::HashMap;
use std::fmt;

/// The PLC's `status` field.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum StatusCode {
    /// 0: nothing going on.
    Idle,
    /// 1: validating or applying a commit.
    Busy,
    /// 2: the table with `status_sequence` was accepted and is active.
    Accepted,
    /// 3: the table with `status_sequence` was rejected (`error_code` says why).
    Rejected,
    /// Any other value.
    Other(u16),
}

impl StatusCode {
    pub fn code(self) -> u16 {
        match self {
            StatusCode::Idle => 0,
            StatusCode::Busy => 1,
            StatusCode::Accepted => 2,
            StatusCode::Rejected => 3,
            StatusCode::Other(c) => c,
        }
    }
    /// The status in a word ("idle", "busy", "accepted", "rejected", or "code N").
    pub fn words(self) -> String {
        match self {
            StatusCode::Idle => "idle".into(),
            StatusCode::Busy => "busy".into(),
            StatusCode::Accepted => "accepted".into(),
            StatusCode::Rejected => "rejected".into(),
            StatusCode::Other(c) => format!("code {c}"),
        }
    }

    pub fn from_code(c: u16) -> Self {
        match c {
            0 => StatusCode::Idle,
            1 => StatusCode::Busy,
            2 => StatusCode::Accepted,
            3 => StatusCode::Rejected,
            c => StatusCode::Other(c),
        }
    }
}

/// The fields the PLC writes, decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlcStatus {
    /// 1 = ready.
    pub ready: u16,
    pub heartbeat: u16,
    pub status: StatusCode,
    pub error_code: u16,
    pub status_sequence: u32,
    pub active_sequence: u32,
}

impl PlcStatus {
    /// Whether `plc_ready` says ready (exactly 1).
    pub fn is_ready(&self) -> bool {
        self.ready == 1
    }

    /// Decode from register images of both tables (`holding(a)`, `input(a)`).
    pub fn decode(
        map: &CncMap,
        holding: &dyn Fn(u16) -> u16,
        input: &dyn Fn(u16) -> u16,
    ) -> PlcStatus {
        let get = |f: &Field| -> f64 {
            match f.kind {
                RegisterKind::Holding => table::read_field(f, holding),
                RegisterKind::Input => table::read_field(f, input),
            }
        };
        let h = &map.handshake;
        PlcStatus {
            ready: get(&h.plc_ready) as u16,
            heartbeat: get(&h.plc_heartbeat) as u16,
            status: StatusCode::from_code(get(&h.status) as u16),
            error_code: get(&h.error_code) as u16,
            status_sequence: get(&h.status_sequence) as u32,
            active_sequence: get(&h.active_sequence) as u32,
        }
    }

    /// The registers of each field (kind, address, registers), as the PLC writes them.
    /// Sequences wrap to the field's type (a u16 sequence field holds the low 16 bits).
    pub fn encode(&self, map: &CncMap) -> Vec<(RegisterKind, u16, Vec<u16>)> {
        let h = &map.handshake;
        let put = |f: &Field, v: u32| {
            let v = if f.ty.words() == 1 { v & 0xFFFF } else { v };
            let mut r = vec![0u16; f.words() as usize];
            // Every value fits: u16 fields get ≤ 0xFFFF, u32 fields any u32.
            let _ = codec::encode(f.ty, f.order, v as f64, &mut r);
            (f.kind, f.address, r)
        };
        vec![
            put(&h.plc_ready, self.ready as u32),
            put(&h.plc_heartbeat, self.heartbeat as u32),
            put(&h.status, self.status.code() as u32),
            put(&h.error_code, self.error_code as u32),
            put(&h.status_sequence, self.status_sequence),
            put(&h.active_sequence, self.active_sequence),
        ]
    }
}

impl fmt::Display for PlcStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}, heartbeat {}, ",
            if self.is_ready() {
                "ready"
            } else {
                "not ready"
            },
            self.heartbeat
        )?;
        match self.status {
            StatusCode::Idle if self.status_sequence == 0 => write!(f, "idle")?,
            StatusCode::Rejected => write!(
                f,
                "rejected sequence {} ({})",
                self.status_sequence,
                table::RejectCode::from_code(self.error_code)
            )?,
            st => write!(f, "{} sequence {}", st.words(), self.status_sequence)?,
        }
        if self.active_sequence == 0 {
            write!(f, ", empty (no table applied)")
        } else {
            write!(f, ", active sequence {}", self.active_sequence)
        }
    }
}

/// The reads that fetch every PLC-written field: contiguous runs per register table (no
/// reserved registers read, since a PLC may not map them), each at most 125 registers.
pub fn status_reads(map: &CncMap) -> Vec<(RegisterKind, ReadRange)> {
    let mut spans: Vec<(RegisterKind, u32, u32)> = map
        .handshake
        .plc_fields()
        .iter()
        .map(|f| (f.kind, f.address as u32, f.end()))
        .collect();
    spans.sort_by_key(|s| (s.0 == RegisterKind::Input, s.1));
    let mut runs: Vec<(RegisterKind, u32, u32)> = Vec::new();
    for (k, a, e) in spans {
        match runs.last_mut() {
            Some((rk, _, re)) if *rk == k && *re == a => *re = e,
            _ => runs.push((k, a, e)),
        }
    }
    let mut out = Vec::new();
    for (k, a, e) in runs {
        let mut s = a;
        while s < e {
            let n = (e - s).min(codec::MAX_READ as u32);
            // Fields lie inside the address space (the map checked), so the range is valid.
            if let Ok(r) = ReadRange::new(s as u16, n as u16) {
                out.push((k, r));
            }
            s += n;
        }
    }
    out
}

/// A register image filled by reads, answering 0 for registers not read.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Image(HashMap<(RegisterKind, u16), u16>);

impl Image {
    /// Store `values` read from `start` of `kind`.
    pub fn put(&mut self, kind: RegisterKind, start: u16, values: &[u16]) {
        for (k, v) in values.iter().enumerate() {
            self.0.insert((kind, start.wrapping_add(k as u16)), *v);
        }
    }
    pub fn get(&self, kind: RegisterKind, address: u16) -> u16 {
        self.0.get(&(kind, address)).copied().unwrap_or(0)
    }
    /// The PLC status the image holds.
    pub fn status(&self, map: &CncMap) -> PlcStatus {
        PlcStatus::decode(map, &|a| self.get(RegisterKind::Holding, a), &|a| {
            self.get(RegisterKind::Input, a)
        })
    }
}

/// Read the PLC's handshake fields (for `table status` and the console).
pub async fn read_status(link: &Link, map: &CncMap) -> Result<PlcStatus, LinkError> {
    let mut img = Image::default();
    for (kind, r) in status_reads(map) {
        let v = link.read(kind, map.unit_id, r).await?;
        img.put(kind, r.start(), &v);
    }
    Ok(img.status(map))
}

/// What a PLC's staging area holds, read back.
#[derive(Clone, Debug, PartialEq)]
pub struct ReadBack {
    pub status: PlcStatus,
    pub header: table::RawHeader,
    pub counts: Vec<i32>,
    /// The table, or why the PLC would refuse it (its CRC checked against the header's).
    pub table: Result<PlcTable, Reject>,
}

/// Read the PLC's status, header and payload and decode them (for `table status`: what the
/// PLC holds, compared with what the store says was published). The staging area holds the
/// last table written, which is the active one when `status.active_sequence` equals the
/// header's sequence.
pub async fn read_table(link: &Link, map: &CncMap) -> Result<ReadBack, LinkError> {
    let status = read_status(link, map).await?;
    let mut img = Image::default();
    let read = |start: u32, end: u32| {
        let mut spans = Vec::new();
        let mut s = start;
        while s < end {
            let n = (end - s).min(table::MAX_CHUNK as u32);
            spans.push((s as u16, n as u16));
            s += n;
        }
        spans
    };
    let h = &map.header;
    let (lo, hi) = h.fields().iter().fold((u32::MAX, 0), |(lo, hi), f| {
        (lo.min(f.address as u32), hi.max(f.end()))
    });
    for (s, n) in read(lo, hi) {
        let r = ReadRange::new(s, n).map_err(LinkError::Address)?;
        let v = link.read(RegisterKind::Holding, map.unit_id, r).await?;
        img.put(RegisterKind::Holding, s, &v);
    }
    let get = |a: u16| img.get(RegisterKind::Holding, a);
    let header = table::decode_header(map, &get);
    let count = table::payload_len(map, &header);
    let words = map.payload.ty.words() as u32;
    let start = map.payload.address as u32;
    let spans = read(start, start + count as u32 * words);
    for (s, n) in spans {
        let r = ReadRange::new(s, n).map_err(LinkError::Address)?;
        let v = link.read(RegisterKind::Holding, map.unit_id, r).await?;
        img.put(RegisterKind::Holding, s, &v);
    }
    let get = |a: u16| img.get(RegisterKind::Holding, a);
    let counts = table::decode_payload(map, count, &get);
    let table = table::validate(map, &header, &counts, None);
    Ok(ReadBack {
        status,
        header,
        counts,
        table,
    })
}

/// The store's record of a publish result (`store::Publication::outcome`).
pub fn publication_outcome(r: &Result<PublishOutcome, PublishError>) -> PublicationOutcome {
    match r {
        Ok(PublishOutcome::Accepted { .. }) => PublicationOutcome::Accepted,
        Ok(PublishOutcome::Rejected { code, .. }) => PublicationOutcome::Rejected {
            code: Some(code.code() as i64),
            text: code.meaning().to_string(),
        },
        Err(e) => PublicationOutcome::Failed {
            code: match e {
                PublishError::Link {
                    error: LinkError::Exception(x),
                    ..
                } => Some(x.code() as i64),
                _ => None,
            },
            text: e.to_string(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_round_trips_through_registers_for_every_map() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc");
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            let m = CncMap::load(&p).unwrap();
            let st = PlcStatus {
                ready: 1,
                heartbeat: 0xBEEF,
                status: StatusCode::Rejected,
                error_code: 4,
                status_sequence: 70_000,
                active_sequence: 69_999,
            };
            let mut img = Image::default();
            for (k, a, r) in st.encode(&m) {
                img.put(k, a, &r);
            }
            assert_eq!(img.status(&m), st, "{}", p.display());
            // The planned reads cover every PLC field.
            let mut read = Image::default();
            for (k, r) in status_reads(&m) {
                let v: Vec<u16> = (r.start()..r.end() as u16).map(|a| img.get(k, a)).collect();
                read.put(k, r.start(), &v);
            }
            assert_eq!(read.status(&m), st, "{}", p.display());
        }
    }

    #[test]
    fn status_reads_are_contiguous_runs() {
        let g = CncMap::generic().unwrap();
        let r = status_reads(&g);
        assert_eq!(r.len(), 1);
        assert_eq!(
            (r[0].0, r[0].1.start(), r[0].1.count()),
            (RegisterKind::Holding, 0, 8)
        );
        let c = CncMap::load(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc/codesys.toml"),
        )
        .unwrap();
        let r = status_reads(&c);
        assert_eq!(r.len(), 1);
        assert_eq!(
            (r[0].0, r[0].1.start(), r[0].1.count()),
            (RegisterKind::Input, 0, 8)
        );
    }
}
