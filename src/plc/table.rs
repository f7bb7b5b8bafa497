//! The table block (sans-I/O): a compensation table as header and payload registers per a
//! [`CncMap`], and back.
//!
//! - [`PlcTable`] is the table as the PLC protocol carries it: one equally spaced grid (start,
//!   interval, points) and one profile per direction of `e = measured − nominal` (mm), the
//!   crate's one sign. [`PlcTable::from_comp`] fits a `comp::CompTable` onto a grid the map
//!   can hold (the same `comp::fit_grid` the exporters use) and resamples it.
//! - [`encode`] turns it into registers: payload counts `round(s·e / resolution)` with `s = −1`
//!   for the generic protocol's "correction" sign (the value the controller adds to the
//!   commanded position) and `s = +1` for "error"; limit checks on the counts (the PLC sees
//!   counts, so the encoder and the PLC's validation agree exactly) with errors naming the
//!   point and the limit; CRC-32/ISO-HDLC over the payload values' bytes in the map's byte
//!   order (see [`payload_crc`]).
//! - [`decode_header`], [`decode_payload`] and [`validate`] are the PLC side: what the twin's
//!   PLC and the `table status` read-back use, with the protocol's rejection codes.

use super::map::{CncMap, CrcBytes, Field, Sign};
use crate::comp::{CompError, CompTable, GridLimits, MachineAxis, TableKind, TableValues};
use crate::modbus::codec::{self, CodecError, ValueType};
use std::collections::BTreeMap;
use std::fmt;
use thiserror::Error;

/// Most registers one write (or read-back read) carries in a publish: below the protocol's
/// 123 (write) and 125 (read), and a common PLC buffer size (S7 MB_CLIENT-era limits, many
/// gateways).
pub const MAX_CHUNK: u16 = 120;

/// The CRC of the payload: CRC-32/ISO-HDLC (the zlib/Ethernet CRC-32: reflected polynomial
/// 0x04C11DB7, init and xorout 0xFFFFFFFF; check value 0xCBF43926 for "123456789").
pub const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// Which approach direction(s) a table applies to (the header's `direction` code).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TableDirection {
    /// One profile for both directions (code 0).
    Both,
    /// Only when approaching towards increasing position (code 1).
    Positive,
    /// Only when approaching towards decreasing position (code 2).
    Negative,
    /// Two profiles in the payload: + then − (code 3).
    Bidirectional,
}

impl TableDirection {
    /// In words, for messages: "both directions", "increasing only", …
    pub fn words(self) -> &'static str {
        match self {
            TableDirection::Both => "both directions, one profile",
            TableDirection::Positive => "increasing only",
            TableDirection::Negative => "decreasing only",
            TableDirection::Bidirectional => "bidirectional, two profiles",
        }
    }

    pub fn code(self) -> u16 {
        match self {
            TableDirection::Both => 0,
            TableDirection::Positive => 1,
            TableDirection::Negative => 2,
            TableDirection::Bidirectional => 3,
        }
    }
    pub fn from_code(c: u16) -> Option<Self> {
        Some(match c {
            0 => TableDirection::Both,
            1 => TableDirection::Positive,
            2 => TableDirection::Negative,
            3 => TableDirection::Bidirectional,
            _ => return None,
        })
    }
    /// Profiles in the payload.
    pub fn profiles(self) -> usize {
        if self == TableDirection::Bidirectional {
            2
        } else {
            1
        }
    }
}

/// The header's `kind` code: 1 positioning, 2 straightness, 3 Abbe.
pub fn kind_code(k: TableKind) -> u16 {
    match k {
        TableKind::Positioning => 1,
        TableKind::Straightness => 2,
        TableKind::Abbe => 3,
    }
}

pub fn kind_from_code(c: u16) -> Option<TableKind> {
    Some(match c {
        1 => TableKind::Positioning,
        2 => TableKind::Straightness,
        3 => TableKind::Abbe,
        _ => return None,
    })
}

/// The header's axis codes: 1 X, 2 Y, 3 Z.
pub fn axis_code(a: MachineAxis) -> u16 {
    a.index() as u16 + 1
}

pub fn axis_from_code(c: u16) -> Option<MachineAxis> {
    MachineAxis::ALL.get((c as usize).checked_sub(1)?).copied()
}

/// A table as the PLC protocol carries it.
#[derive(Clone, Debug, PartialEq)]
pub struct PlcTable {
    pub kind: TableKind,
    /// The axis the values act on.
    pub axis: MachineAxis,
    /// The axis whose position indexes the table.
    pub base_axis: MachineAxis,
    pub direction: TableDirection,
    /// Position of the first point (mm).
    pub start_mm: f64,
    /// Spacing (mm, > 0).
    pub interval_mm: f64,
    /// `e = measured − nominal` (mm) per point: the + profile (or the only one).
    pub values_mm: Vec<f64>,
    /// The − profile, for `Bidirectional` only.
    pub down_mm: Option<Vec<f64>>,
}

impl PlcTable {
    /// The grid's positions (mm).
    pub fn positions(&self) -> Vec<f64> {
        (0..self.values_mm.len())
            .map(|k| self.start_mm + k as f64 * self.interval_mm)
            .collect()
    }

    /// Fit `table` onto a grid `map` can hold and resample it: at most `max_points` points,
    /// the spacing a multiple of the header's position resolution (`step_mm` wanted, default
    /// the table's mean spacing), the start on that resolution too. A single profile with a
    /// backlash becomes a bidirectional table (− profile = + profile + backlash, what
    /// `CompTable::reverse` gives), so both directions are published in one commit.
    pub fn from_comp(
        table: &CompTable,
        map: &CncMap,
        step_mm: Option<f64>,
    ) -> Result<PlcTable, TableError> {
        let q = position_quantum(map);
        let limits = GridLimits {
            max_points: map.limits.max_points as usize,
            min_step_mm: q,
            step_quantum_mm: q,
            step_mm,
        };
        let grid = crate::comp::fit_grid(table, &limits, "plc")
            .map_err(|e: CompError| TableError::Grid(e.to_string()))?;
        let start = (grid.start_mm / q).round() * q;
        let positions: Vec<f64> = (0..grid.count)
            .map(|k| start + k as f64 * grid.step_mm)
            .collect();
        let r = table.resample(&positions);
        let (direction, values_mm, down_mm) = match &r.values {
            TableValues::Single {
                values,
                backlash_mm: None,
            } => (TableDirection::Both, values.clone(), None),
            TableValues::Single {
                values,
                backlash_mm: Some(_),
            } => (
                TableDirection::Bidirectional,
                values.clone(),
                Some(r.reverse()),
            ),
            TableValues::Bidirectional { up, down } => (
                TableDirection::Bidirectional,
                up.clone(),
                Some(down.clone()),
            ),
        };
        Ok(PlcTable {
            kind: table.kind,
            axis: table.comp_axis,
            base_axis: table.base_axis,
            direction,
            start_mm: start,
            interval_mm: grid.step_mm,
            values_mm,
            down_mm,
        })
    }
}

/// The resolution the grid must sit on (mm): the coarser of start's and interval's (an f32
/// field has no fixed resolution: 0.1 µm is used).
pub fn position_quantum(map: &CncMap) -> f64 {
    let q = |f: &Field| {
        if f.ty == ValueType::F32 {
            1e-4
        } else {
            f.mm_per_count
        }
    };
    q(&map.header.start).max(q(&map.header.interval))
}

/// Why a table cannot be encoded (nothing is sent).
#[derive(Clone, Debug, Error, PartialEq)]
pub enum TableError {
    #[error(
        "the table has {points} points; the PLC takes 2 to {max} (limits.max_points): refit the grid"
    )]
    Points { points: usize, max: u16 },
    #[error("a table of {} needs {need} profile(s) of equal length; got {got}", direction.words())]
    Profiles {
        direction: TableDirection,
        need: usize,
        got: String,
    },
    #[error(
        "{what} = {value_mm} mm is not a multiple of the field's resolution {resolution_mm} mm: fit the grid to it (PlcTable::from_comp does)"
    )]
    NotOnResolution {
        what: &'static str,
        value_mm: f64,
        resolution_mm: f64,
    },
    #[error("the interval {0} mm is not positive")]
    Interval(f64),
    #[error("{profile} point {point} at {position_mm:.4} mm is not a finite value")]
    NotFinite {
        profile: &'static str,
        point: usize,
        position_mm: f64,
    },
    #[error(
        "{profile} point {point} at {position_mm:.4} mm: |{value_um:.2} µm| exceeds the PLC's limit {limit_um} µm (limits.max_abs_um in {file}); check the table, or raise the limit if the PLC takes it"
    )]
    ValueLimit {
        profile: &'static str,
        point: usize,
        position_mm: f64,
        value_um: f64,
        limit_um: f64,
        file: String,
    },
    #[error(
        "{profile} points {from}..{to} at {position_mm:.4} mm: a step of {step_um:.2} µm exceeds the PLC's limit {limit_um} µm (limits.max_step_um in {file}); use a finer grid or check the table"
    )]
    StepLimit {
        profile: &'static str,
        from: usize,
        to: usize,
        position_mm: f64,
        step_um: f64,
        limit_um: f64,
        file: String,
    },
    #[error("sequence {sequence}: {problem}")]
    Sequence { sequence: u32, problem: String },
    #[error("{key}: {source}")]
    Field {
        key: &'static str,
        source: CodecError,
    },
    #[error("grid: {0}")]
    Grid(String),
}

/// The registers of one encoded table.
#[derive(Clone, Debug, PartialEq)]
pub struct Encoded {
    pub sequence: u32,
    pub crc: u32,
    pub points: u16,
    /// The payload values as counts, in payload order (+ profile, then − profile).
    pub counts: Vec<i32>,
    /// Header fields: (key, address, registers).
    pub header: Vec<(&'static str, u16, Vec<u16>)>,
    /// Payload registers from `map.payload.address`.
    pub payload: Vec<u16>,
    /// The commit word's registers (the sequence).
    pub commit: Vec<u16>,
    payload_address: u16,
}

impl Encoded {
    /// Every register of the header and payload (not the commit word), by address.
    pub fn registers(&self) -> BTreeMap<u16, u16> {
        let mut m = BTreeMap::new();
        for (_, a, regs) in &self.header {
            for (k, r) in regs.iter().enumerate() {
                m.insert(a + k as u16, *r);
            }
        }
        for (k, r) in self.payload.iter().enumerate() {
            m.insert(self.payload_address + k as u16, *r);
        }
        m
    }

    /// The writes of a publish, in order: the header's contiguous runs, then the payload, each
    /// cut into chunks of at most `max` registers (payload chunks start at even offsets from
    /// the payload start when `max` is even, so no 32-bit value is split).
    pub fn chunks(&self, max: u16) -> Vec<(u16, Vec<u16>)> {
        let max = max.clamp(1, MAX_CHUNK) as usize;
        let mut runs: Vec<(u16, Vec<u16>)> = Vec::new();
        let mut header: Vec<&(&'static str, u16, Vec<u16>)> = self.header.iter().collect();
        header.sort_by_key(|h| h.1);
        for (_, a, regs) in header {
            match runs.last_mut() {
                Some((s, v)) if *s as usize + v.len() == *a as usize => v.extend(regs),
                _ => runs.push((*a, regs.clone())),
            }
        }
        runs.push((self.payload_address, self.payload.clone()));
        let mut out = Vec::new();
        for (start, regs) in runs {
            for (k, c) in regs.chunks(max).enumerate() {
                out.push((start + (k * max) as u16, c.to_vec()));
            }
        }
        out
    }

    /// The key of the field (or payload value) at `address`, for messages.
    pub fn key_at(&self, address: u16) -> String {
        for (key, a, regs) in &self.header {
            if (*a..*a + regs.len() as u16).contains(&address) {
                return (*key).to_string();
            }
        }
        let k = address.saturating_sub(self.payload_address) as usize;
        let per = (self.payload.len() / self.counts.len().max(1)).max(1);
        format!("payload[{}]", k / per)
    }
}

pub(crate) fn field_regs(f: &Field, value: f64) -> Result<Vec<u16>, TableError> {
    let mut out = vec![0u16; f.words() as usize];
    codec::encode(f.ty, f.order, value, &mut out)
        .map_err(|source| TableError::Field { key: f.key, source })?;
    Ok(out)
}

/// A sequence's registers in `f` (commit, header sequence, …): 1..=65535 for u16 fields,
/// nonzero for u32 (0 means "no table").
pub fn sequence_regs(f: &Field, sequence: u32) -> Result<Vec<u16>, TableError> {
    if sequence == 0 {
        return Err(TableError::Sequence {
            sequence,
            problem: "0 means \"no table\": start sequences at 1".into(),
        });
    }
    let (_, max) = f.ty.range();
    if sequence as f64 > max {
        return Err(TableError::Sequence {
            sequence,
            problem: format!("does not fit {} ({}): wrap sequences at {max}", f.key, f.ty),
        });
    }
    field_regs(f, sequence as f64)
}

/// The CRC-32/ISO-HDLC of payload `counts` as `ty` values, each value's two's-complement
/// bytes in `order`, in payload order.
pub fn payload_crc(counts: &[i32], ty: ValueType, order: CrcBytes) -> u32 {
    let mut d = CRC32.digest();
    for &c in counts {
        match (ty, order) {
            (ValueType::I16, CrcBytes::BigEndian) => d.update(&(c as i16).to_be_bytes()),
            (ValueType::I16, CrcBytes::LittleEndian) => d.update(&(c as i16).to_le_bytes()),
            (_, CrcBytes::BigEndian) => d.update(&c.to_be_bytes()),
            (_, CrcBytes::LittleEndian) => d.update(&c.to_le_bytes()),
        }
    }
    d.finalize()
}

fn sign(map: &CncMap) -> f64 {
    match map.payload.sign {
        Sign::Correction => -1.0,
        Sign::Error => 1.0,
    }
}

/// Largest |count| and |step| (counts) the limits allow at the payload's resolution.
pub fn count_limits(map: &CncMap) -> (i64, i64) {
    let r = map.payload.mm_per_count;
    (
        (map.limits.max_abs_mm / r + 1e-9).floor() as i64,
        (map.limits.max_step_mm / r + 1e-9).floor() as i64,
    )
}

fn on_resolution(what: &'static str, v: f64, f: &Field) -> Result<f64, TableError> {
    if f.ty == ValueType::F32 {
        return Ok(v / f.mm_per_count);
    }
    let counts = v / f.mm_per_count;
    if (counts - counts.round()).abs() > 1e-3 {
        return Err(TableError::NotOnResolution {
            what,
            value_mm: v,
            resolution_mm: f.mm_per_count,
        });
    }
    Ok(counts.round())
}

/// Encode `table` with `sequence` per `map`.
pub fn encode(table: &PlcTable, map: &CncMap, sequence: u32) -> Result<Encoded, TableError> {
    let n = table.values_mm.len();
    if !(2..=map.limits.max_points as usize).contains(&n) {
        return Err(TableError::Points {
            points: n,
            max: map.limits.max_points,
        });
    }
    let profiles: Vec<(&'static str, &[f64])> = match (table.direction, &table.down_mm) {
        (TableDirection::Bidirectional, Some(d)) if d.len() == n => {
            vec![("+", &table.values_mm[..]), ("-", &d[..])]
        }
        (TableDirection::Bidirectional, d) => {
            return Err(TableError::Profiles {
                direction: table.direction,
                need: 2,
                got: match d {
                    Some(d) => format!("{n} and {}", d.len()),
                    None => format!("{n} and none"),
                },
            });
        }
        (dir, None) => {
            let name = match dir {
                TableDirection::Negative => "-",
                TableDirection::Positive => "+",
                _ => "both",
            };
            vec![(name, &table.values_mm[..])]
        }
        (dir, Some(_)) => {
            return Err(TableError::Profiles {
                direction: dir,
                need: 1,
                got: "a − profile too".into(),
            });
        }
    };
    if !(table.interval_mm.is_finite() && table.interval_mm > 0.0) {
        return Err(TableError::Interval(table.interval_mm));
    }
    let h = &map.header;
    let start = on_resolution("start", table.start_mm, &h.start)?;
    let interval = on_resolution("interval", table.interval_mm, &h.interval)?;
    let res = map.payload.mm_per_count;
    let s = sign(map);
    let (max_abs, max_step) = count_limits(map);
    let mut counts = Vec::with_capacity(n * profiles.len());
    for (name, values) in &profiles {
        let mut prev: Option<i64> = None;
        for (k, &v) in values.iter().enumerate() {
            let position_mm = table.start_mm + k as f64 * table.interval_mm;
            if !v.is_finite() {
                return Err(TableError::NotFinite {
                    profile: name,
                    point: k,
                    position_mm,
                });
            }
            let c = (s * v / res).round() as i64;
            if c.abs() > max_abs {
                return Err(TableError::ValueLimit {
                    profile: name,
                    point: k,
                    position_mm,
                    value_um: v * 1e3,
                    limit_um: map.limits.max_abs_mm * 1e3,
                    file: map.file.clone(),
                });
            }
            if let Some(p) = prev
                && (c - p).abs() > max_step
            {
                return Err(TableError::StepLimit {
                    profile: name,
                    from: k - 1,
                    to: k,
                    position_mm,
                    step_um: (c - p) as f64 * res * 1e3,
                    limit_um: map.limits.max_step_mm * 1e3,
                    file: map.file.clone(),
                });
            }
            prev = Some(c);
            // |c| ≤ max_abs, which the map checked fits the payload type.
            counts.push(c as i32);
        }
    }
    let p = &map.payload;
    let crc = payload_crc(&counts, p.ty, p.crc_bytes);
    let header = vec![
        (
            h.kind.key,
            h.kind.address,
            field_regs(&h.kind, kind_code(table.kind) as f64)?,
        ),
        (
            h.axis.key,
            h.axis.address,
            field_regs(&h.axis, axis_code(table.axis) as f64)?,
        ),
        (
            h.base_axis.key,
            h.base_axis.address,
            field_regs(&h.base_axis, axis_code(table.base_axis) as f64)?,
        ),
        (
            h.direction.key,
            h.direction.address,
            field_regs(&h.direction, table.direction.code() as f64)?,
        ),
        (
            h.points.key,
            h.points.address,
            field_regs(&h.points, n as f64)?,
        ),
        (
            h.unit.key,
            h.unit.address,
            field_regs(&h.unit, p.unit_nm as f64)?,
        ),
        (h.start.key, h.start.address, field_regs(&h.start, start)?),
        (
            h.interval.key,
            h.interval.address,
            field_regs(&h.interval, interval)?,
        ),
        (
            h.sequence.key,
            h.sequence.address,
            sequence_regs(&h.sequence, sequence)?,
        ),
        (h.crc.key, h.crc.address, field_regs(&h.crc, crc as f64)?),
    ];
    let words = p.ty.words() as usize;
    let mut payload = vec![0u16; counts.len() * words];
    for (k, &c) in counts.iter().enumerate() {
        codec::encode(p.ty, p.order, c as f64, &mut payload[k * words..]).map_err(|source| {
            TableError::Field {
                key: "payload",
                source,
            }
        })?;
    }
    Ok(Encoded {
        sequence,
        crc,
        points: n as u16,
        counts,
        header,
        payload,
        commit: sequence_regs(&map.handshake.commit, sequence)?,
        payload_address: p.address,
    })
}

// ---------- the PLC side ----------

/// The header as registers hold it (codes not yet interpreted).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawHeader {
    pub kind: u16,
    pub axis: u16,
    pub base_axis: u16,
    pub direction: u16,
    pub points: u16,
    pub unit: u16,
    pub start_mm: f64,
    pub interval_mm: f64,
    pub sequence: u32,
    pub crc: u32,
}

/// A field's value from a register image (`regs(address)`, missing registers read 0).
pub fn read_field(f: &Field, regs: &dyn Fn(u16) -> u16) -> f64 {
    let r: Vec<u16> = (0..f.words()).map(|k| regs(f.address + k)).collect();
    // The slice is as long as the type needs, so decoding cannot fail.
    codec::decode(f.ty, f.order, &r).unwrap_or(0.0)
}

fn read_u32(f: &Field, regs: &dyn Fn(u16) -> u16) -> u32 {
    read_field(f, regs) as u32
}

fn read_u16(f: &Field, regs: &dyn Fn(u16) -> u16) -> u16 {
    read_field(f, regs) as u16
}

/// The header from a holding-register image.
pub fn decode_header(map: &CncMap, regs: &dyn Fn(u16) -> u16) -> RawHeader {
    let h = &map.header;
    let length = |f: &Field| read_field(f, regs) * f.mm_per_count;
    RawHeader {
        kind: read_u16(&h.kind, regs),
        axis: read_u16(&h.axis, regs),
        base_axis: read_u16(&h.base_axis, regs),
        direction: read_u16(&h.direction, regs),
        points: read_u16(&h.points, regs),
        unit: read_u16(&h.unit, regs),
        start_mm: length(&h.start),
        interval_mm: length(&h.interval),
        sequence: read_u32(&h.sequence, regs),
        crc: read_u32(&h.crc, regs),
    }
}

/// Payload values a header announces (points × profiles), capped at the map's capacity.
pub fn payload_len(map: &CncMap, header: &RawHeader) -> usize {
    let profiles = TableDirection::from_code(header.direction).map_or(1, |d| d.profiles());
    let cap = map.payload.capacity as usize / map.payload.ty.words() as usize;
    (header.points as usize * profiles).min(cap)
}

/// `count` payload values (counts) from a holding-register image.
pub fn decode_payload(map: &CncMap, count: usize, regs: &dyn Fn(u16) -> u16) -> Vec<i32> {
    let p = &map.payload;
    let words = p.ty.words();
    (0..count)
        .map(|k| {
            let a = p.address as u32 + k as u32 * words as u32;
            let r: Vec<u16> = (0..words as u32)
                .map(|w| regs(u16::try_from(a + w).unwrap_or(u16::MAX)))
                .collect();
            codec::decode(p.ty, p.order, &r).unwrap_or(0.0) as i32
        })
        .collect()
}

/// The protocol's rejection codes (the PLC writes them to `error_code`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RejectCode {
    /// 1: the payload's CRC does not match the header's.
    Crc,
    /// 2: the header's sequence is not the committed one.
    Sequence,
    /// 3: point count outside 2..=max_points.
    Points,
    /// 4: a value beyond max |value|.
    ValueLimit,
    /// 5: a step beyond the max step.
    StepLimit,
    /// 6: kind, axis or direction unknown or not handled by this PLC.
    Unsupported,
    /// 7: interval not positive.
    Interval,
    /// 8: the payload unit (resolution) is not the PLC's.
    Unit,
    /// 9: the PLC cannot take a table now (machine busy).
    NotReady,
    /// Any other code (site-specific codes from 256 on).
    Other(u16),
}

impl RejectCode {
    pub fn code(self) -> u16 {
        match self {
            RejectCode::Crc => 1,
            RejectCode::Sequence => 2,
            RejectCode::Points => 3,
            RejectCode::ValueLimit => 4,
            RejectCode::StepLimit => 5,
            RejectCode::Unsupported => 6,
            RejectCode::Interval => 7,
            RejectCode::Unit => 8,
            RejectCode::NotReady => 9,
            RejectCode::Other(c) => c,
        }
    }

    pub fn from_code(c: u16) -> Self {
        match c {
            1 => RejectCode::Crc,
            2 => RejectCode::Sequence,
            3 => RejectCode::Points,
            4 => RejectCode::ValueLimit,
            5 => RejectCode::StepLimit,
            6 => RejectCode::Unsupported,
            7 => RejectCode::Interval,
            8 => RejectCode::Unit,
            9 => RejectCode::NotReady,
            c => RejectCode::Other(c),
        }
    }

    /// What the code means.
    pub fn meaning(self) -> &'static str {
        match self {
            RejectCode::Crc => "CRC mismatch",
            RejectCode::Sequence => "header sequence is not the committed one",
            RejectCode::Points => "point count out of range",
            RejectCode::ValueLimit => "value beyond the PLC's limit",
            RejectCode::StepLimit => "step between points beyond the PLC's limit",
            RejectCode::Unsupported => "kind, axis or direction not supported",
            RejectCode::Interval => "interval not positive",
            RejectCode::Unit => "payload unit not the PLC's",
            RejectCode::NotReady => "the PLC cannot take a table now",
            RejectCode::Other(_) => "site-specific code",
        }
    }
}

impl fmt::Display for RejectCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "code {} ({})", self.code(), self.meaning())
    }
}

/// A table the PLC side refuses, with its code and the detail.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("{code}: {detail}")]
pub struct Reject {
    pub code: RejectCode,
    pub detail: String,
}

fn reject(code: RejectCode, detail: impl Into<String>) -> Reject {
    Reject {
        code,
        detail: detail.into(),
    }
}

/// Validate a staged table as the PLC does on commit, and convert it back to a [`PlcTable`]
/// (`e = measured − nominal`, mm). `commit` is the committed sequence (`None`: skip the
/// sequence check, e.g. for a read-back).
pub fn validate(
    map: &CncMap,
    header: &RawHeader,
    counts: &[i32],
    commit: Option<u32>,
) -> Result<PlcTable, Reject> {
    if let Some(c) = commit
        && header.sequence != c
    {
        return Err(reject(
            RejectCode::Sequence,
            format!("header sequence {} ≠ commit {c}", header.sequence),
        ));
    }
    let n = header.points as usize;
    if !(2..=map.limits.max_points as usize).contains(&n) {
        return Err(reject(
            RejectCode::Points,
            format!("{n} points, not 2 to {}", map.limits.max_points),
        ));
    }
    let kind = kind_from_code(header.kind)
        .ok_or_else(|| reject(RejectCode::Unsupported, format!("kind {}", header.kind)))?;
    let axis = axis_from_code(header.axis)
        .ok_or_else(|| reject(RejectCode::Unsupported, format!("axis {}", header.axis)))?;
    let base_axis = axis_from_code(header.base_axis).ok_or_else(|| {
        reject(
            RejectCode::Unsupported,
            format!("base axis {}", header.base_axis),
        )
    })?;
    let direction = TableDirection::from_code(header.direction).ok_or_else(|| {
        reject(
            RejectCode::Unsupported,
            format!("direction {}", header.direction),
        )
    })?;
    if header.unit != map.payload.unit_nm {
        return Err(reject(
            RejectCode::Unit,
            format!("{} nm per count, not {}", header.unit, map.payload.unit_nm),
        ));
    }
    if !(header.interval_mm.is_finite() && header.interval_mm > 0.0) {
        return Err(reject(
            RejectCode::Interval,
            format!("{} mm", header.interval_mm),
        ));
    }
    if counts.len() != n * direction.profiles() {
        return Err(reject(
            RejectCode::Points,
            format!(
                "{} payload values for {n} points × {} profile(s)",
                counts.len(),
                direction.profiles()
            ),
        ));
    }
    let crc = payload_crc(counts, map.payload.ty, map.payload.crc_bytes);
    if crc != header.crc {
        return Err(reject(
            RejectCode::Crc,
            format!("payload CRC 0x{crc:08X} ≠ header 0x{:08X}", header.crc),
        ));
    }
    let (max_abs, max_step) = count_limits(map);
    for (p, profile) in counts.chunks(n).enumerate() {
        for (k, &c) in profile.iter().enumerate() {
            if (c as i64).abs() > max_abs {
                return Err(reject(
                    RejectCode::ValueLimit,
                    format!("profile {p} point {k}: {c} counts, limit {max_abs}"),
                ));
            }
            if k > 0 && (c as i64 - profile[k - 1] as i64).abs() > max_step {
                return Err(reject(
                    RejectCode::StepLimit,
                    format!("profile {p} points {}..{k}: step limit {max_step}", k - 1),
                ));
            }
        }
    }
    let s = sign(map);
    let res = map.payload.mm_per_count;
    let mm = |c: &[i32]| -> Vec<f64> { c.iter().map(|&c| s * c as f64 * res).collect() };
    Ok(PlcTable {
        kind,
        axis,
        base_axis,
        direction,
        start_mm: header.start_mm,
        interval_mm: header.interval_mm,
        values_mm: mm(&counts[..n]),
        down_mm: (direction == TableDirection::Bidirectional).then(|| mm(&counts[n..])),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::comp::MachineAxis::*;
    use crate::modbus::WordOrder;

    fn generic() -> CncMap {
        CncMap::generic().unwrap()
    }

    fn table(values_um: &[f64]) -> PlcTable {
        PlcTable {
            kind: TableKind::Positioning,
            axis: Y,
            base_axis: Y,
            direction: TableDirection::Both,
            start_mm: -10.0,
            interval_mm: 25.0,
            values_mm: values_um.iter().map(|v| v * 1e-3).collect(),
            down_mm: None,
        }
    }

    #[test]
    fn crc_is_iso_hdlc() {
        assert_eq!(CRC32.checksum(b"123456789"), 0xCBF4_3926);
        // The payload CRC is the CRC of the values' bytes in the stated order.
        let counts = [1, -2, 0x0102_0304];
        let be: Vec<u8> = counts.iter().flat_map(|c: &i32| c.to_be_bytes()).collect();
        let le: Vec<u8> = counts.iter().flat_map(|c: &i32| c.to_le_bytes()).collect();
        assert_eq!(
            payload_crc(&counts, ValueType::I32, CrcBytes::BigEndian),
            CRC32.checksum(&be)
        );
        assert_eq!(
            payload_crc(&counts, ValueType::I32, CrcBytes::LittleEndian),
            CRC32.checksum(&le)
        );
        assert_eq!(
            payload_crc(&[1, -2], ValueType::I16, CrcBytes::BigEndian),
            CRC32.checksum(&[0x00, 0x01, 0xFF, 0xFE])
        );
        // An empty payload has the CRC of no bytes.
        assert_eq!(payload_crc(&[], ValueType::I32, CrcBytes::BigEndian), 0);
    }

    /// The generic map against registers written out by hand.
    #[test]
    fn generic_encoding_literal_registers() {
        let m = generic();
        // e = +1.5 µm, −0.26 µm, +12.34 µm; correction sign and 0.1 µm: −15, 3 (2.6 → 3), −123.
        let t = table(&[1.5, -0.26, 12.34]);
        let e = encode(&t, &m, 0x0001_0002).unwrap();
        assert_eq!(e.counts, [-15, 3, -123]);
        let be: Vec<u8> = [-15i32, 3, -123]
            .iter()
            .flat_map(|c| c.to_be_bytes())
            .collect();
        assert_eq!(e.crc, CRC32.checksum(&be));
        let regs = e.registers();
        let at = |a: u16| regs[&a];
        assert_eq!(
            (16..22).map(at).collect::<Vec<_>>(),
            [1, 2, 2, 0, 3, 100],
            "kind positioning, axis Y, base Y, both, 3 points, 100 nm"
        );
        // start −10 mm = −100000 counts of 0.1 µm = 0xFFFE_7960; interval 25 mm = 250000 =
        // 0x0003_D090.
        assert_eq!([at(22), at(23)], [0xFFFE, 0x7960]);
        assert_eq!([at(24), at(25)], [0x0003, 0xD090]);
        assert_eq!([at(26), at(27)], [0x0001, 0x0002]);
        assert_eq!([at(28), at(29)], [(e.crc >> 16) as u16, e.crc as u16]);
        // −15 = 0xFFFF_FFF1, 3, −123 = 0xFFFF_FF85.
        assert_eq!(e.payload, [0xFFFF, 0xFFF1, 0x0000, 0x0003, 0xFFFF, 0xFF85]);
        assert_eq!(e.commit, [0x0001, 0x0002]);
        assert!(!regs.contains_key(&30) && !regs.contains_key(&31));
    }

    fn with_order(order: WordOrder) -> CncMap {
        let mut m = generic();
        for f in [
            &mut m.header.start,
            &mut m.header.interval,
            &mut m.header.sequence,
            &mut m.header.crc,
            &mut m.handshake.commit,
        ] {
            f.order = order;
        }
        m.payload.order = order;
        m
    }

    #[test]
    fn word_orders_literal_registers() {
        // −100000 = 0xFFFE_7960 (bytes A=FF B=FE C=79 D=60) in each order.
        let want = [
            (WordOrder::Abcd, [0xFFFE, 0x7960]),
            (WordOrder::Cdab, [0x7960, 0xFFFE]),
            (WordOrder::Badc, [0xFEFF, 0x6079]),
            (WordOrder::Dcba, [0x6079, 0xFEFF]),
        ];
        for (order, start) in want {
            let m = with_order(order);
            let e = encode(&table(&[0.0, 1.0]), &m, 7).unwrap();
            let regs = e.registers();
            assert_eq!([regs[&22], regs[&23]], start, "{order}");
            // −10 counts = 0xFFFF_FFF6.
            let p = match order {
                WordOrder::Abcd => [0xFFFF, 0xFFF6],
                WordOrder::Cdab => [0xFFF6, 0xFFFF],
                WordOrder::Badc => [0xFFFF, 0xF6FF],
                WordOrder::Dcba => [0xF6FF, 0xFFFF],
            };
            assert_eq!(e.payload[2..4], p, "{order}");
            // 16-bit codes only swap bytes in BADC/DCBA (when the field says so).
            assert_eq!(regs[&16], 1);
            // Decoding gives the table back.
            let get = |a: u16| regs.get(&a).copied().unwrap_or(0);
            let h = decode_header(&m, &get);
            assert_eq!(h.sequence, 7);
            assert_eq!((h.start_mm, h.interval_mm), (-10.0, 25.0));
            let c = decode_payload(&m, payload_len(&m, &h), &get);
            assert_eq!(c, [0, -10]);
            let back = validate(&m, &h, &c, Some(7)).unwrap();
            assert_eq!(back.values_mm[0], 0.0);
            assert!((back.values_mm[1] - 1e-3).abs() < 1e-15);
        }
    }

    #[test]
    fn bidirectional_payload_is_up_then_down() {
        let m = generic();
        let mut t = table(&[0.0, 1.0, 2.0]);
        t.direction = TableDirection::Bidirectional;
        t.down_mm = Some(vec![0.005, 0.006, 0.007]);
        let e = encode(&t, &m, 3).unwrap();
        assert_eq!(e.counts, [0, -10, -20, -50, -60, -70]);
        assert_eq!(e.registers()[&19], 3);
        let regs = e.registers();
        let get = |a: u16| regs.get(&a).copied().unwrap_or(0);
        let h = decode_header(&m, &get);
        assert_eq!(payload_len(&m, &h), 6);
        let back = validate(&m, &h, &decode_payload(&m, 6, &get), Some(3)).unwrap();
        let down = back.down_mm.unwrap();
        for (d, w) in down.iter().zip([0.005, 0.006, 0.007]) {
            assert!((d - w).abs() < 1e-15, "{down:?}");
        }
        t.down_mm = Some(vec![0.0]);
        assert!(matches!(
            encode(&t, &m, 3),
            Err(TableError::Profiles { .. })
        ));
    }

    #[test]
    fn limits_name_the_point_and_the_limit() {
        let m = generic();
        let mut v = vec![0.0; 10];
        v[6] = 100.06; // a step of 1001 counts, limit 1000
        let e = encode(&table(&v), &m, 1).unwrap_err();
        let TableError::StepLimit { from, to, .. } = &e else {
            panic!("{e}")
        };
        assert_eq!((*from, *to), (5, 6));
        assert!(e.to_string().contains("limits.max_step_um"), "{e}");
        let mut v: Vec<f64> = (0..12).map(|k| 99.0 * k as f64).collect();
        v[11] = 1000.06;
        let e = encode(&table(&v), &m, 1).unwrap_err();
        let TableError::ValueLimit {
            point, position_mm, ..
        } = &e
        else {
            panic!("{e}")
        };
        assert_eq!((*point, *position_mm), (11, 265.0));
        assert!(e.to_string().contains("point 11 at 265.0000 mm"), "{e}");
        // Exactly at the limit passes.
        let v: Vec<f64> = (0..11).map(|k| 100.0 * k as f64).collect();
        assert!(encode(&table(&v), &m, 1).is_ok());
        assert!(matches!(
            encode(&table(&[1.0]), &m, 1),
            Err(TableError::Points { points: 1, .. })
        ));
        assert!(matches!(
            encode(&table(&[1.0, f64::NAN]), &m, 1),
            Err(TableError::NotFinite { point: 1, .. })
        ));
        let mut t = table(&[0.0, 1.0]);
        t.interval_mm = 25.00003;
        assert!(matches!(
            encode(&t, &m, 1),
            Err(TableError::NotOnResolution {
                what: "interval",
                ..
            })
        ));
        assert!(matches!(
            encode(&table(&[0.0, 1.0]), &m, 0),
            Err(TableError::Sequence { .. })
        ));
    }

    #[test]
    fn the_plc_side_rejects_with_codes() {
        let m = generic();
        let e = encode(&table(&[0.0, 1.0, 2.0]), &m, 9).unwrap();
        let regs = e.registers();
        let get = |a: u16| regs.get(&a).copied().unwrap_or(0);
        let h = decode_header(&m, &get);
        let c = decode_payload(&m, 3, &get);
        assert!(validate(&m, &h, &c, Some(9)).is_ok());
        assert_eq!(
            validate(&m, &h, &c, Some(10)).unwrap_err().code,
            RejectCode::Sequence
        );
        let mut bad = c.clone();
        bad[1] ^= 1;
        assert_eq!(
            validate(&m, &h, &bad, Some(9)).unwrap_err().code,
            RejectCode::Crc
        );
        let mut h2 = h;
        h2.unit = 1000;
        assert_eq!(
            validate(&m, &h2, &c, None).unwrap_err().code,
            RejectCode::Unit
        );
        h2 = h;
        h2.kind = 9;
        assert_eq!(
            validate(&m, &h2, &c, None).unwrap_err().code,
            RejectCode::Unsupported
        );
        h2 = h;
        h2.points = 1;
        assert_eq!(
            validate(&m, &h2, &c[..1], None).unwrap_err().code,
            RejectCode::Points
        );
        // A value beyond the limit, with a matching CRC, is still refused.
        let big = [0, 10_001, 10_001];
        h2 = h;
        h2.crc = payload_crc(&big, ValueType::I32, CrcBytes::BigEndian);
        assert_eq!(
            validate(&m, &h2, &big, None).unwrap_err().code,
            RejectCode::ValueLimit
        );
        for c in 1..=9 {
            assert_eq!(RejectCode::from_code(c).code(), c);
        }
        assert_eq!(RejectCode::from_code(300), RejectCode::Other(300));
    }

    #[test]
    fn chunks_cover_header_then_payload_within_the_limit() {
        let m = generic();
        let v: Vec<f64> = (0..256).map(|k| (k as f64 * 0.37).sin() * 20.0).collect();
        let e = encode(&table(&v), &m, 1).unwrap();
        let chunks = e.chunks(MAX_CHUNK);
        let spans: Vec<(u16, usize)> = chunks.iter().map(|(a, v)| (*a, v.len())).collect();
        assert_eq!(
            spans,
            [
                (16, 14),
                (32, 120),
                (152, 120),
                (272, 120),
                (392, 120),
                (512, 32)
            ]
        );
        let mut all = BTreeMap::new();
        for (a, v) in &chunks {
            for (k, r) in v.iter().enumerate() {
                all.insert(a + k as u16, *r);
            }
        }
        assert_eq!(all, e.registers());
        assert_eq!(e.key_at(20), "header.points");
        assert_eq!(e.key_at(35), "payload[1]");
    }

    #[test]
    fn from_comp_fits_the_grid_and_folds_backlash_into_two_profiles() {
        let m = generic();
        let comp = CompTable {
            kind: TableKind::Positioning,
            name: "EYY".into(),
            base_axis: Y,
            comp_axis: Y,
            reference_mm: 0.0,
            positions_mm: vec![0.0, 10.0, 30.0, 60.0],
            values: TableValues::Single {
                values: vec![0.0, 0.002, -0.001, 0.004],
                backlash_mm: Some(0.003),
            },
        };
        let t = PlcTable::from_comp(&comp, &m, Some(10.0)).unwrap();
        assert_eq!(t.direction, TableDirection::Bidirectional);
        assert_eq!((t.start_mm, t.values_mm.len()), (0.0, 7));
        assert!((t.interval_mm - 10.0).abs() < 1e-9);
        assert!((t.values_mm[2] - 0.0005).abs() < 1e-12, "{:?}", t.values_mm);
        let down = t.down_mm.as_ref().unwrap();
        assert!((down[2] - 0.0035).abs() < 1e-12);
        assert!(encode(&t, &m, 1).is_ok());
        let t = PlcTable::from_comp(&comp, &m, Some(0.123_456)).unwrap();
        assert!(((t.interval_mm / 1e-4).round() * 1e-4 - t.interval_mm).abs() < 1e-12);
        assert!(encode(&t, &m, 1).is_ok());
    }
}
