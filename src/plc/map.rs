//! CNC maps (`plc-maps/cnc/*.toml`, DESIGN §6): where a PLC keeps axiscomp's table block and
//! handshake, field by field. Two stages, as for the I/O maps: the raw TOML (serde,
//! `deny_unknown_fields`), then a validated [`CncMap`]. Every error names the file, the key and
//! what to do. The schema and the protocol are described in `plc-maps/README.md`.
//!
//! Every field has a 0-based PDU address, a register table (holding, or input for fields the
//! PLC writes), a type, a word order, and for lengths a scale and unit. The service writes the
//! header, the payload and the commit word (holding registers); the PLC writes ready, heartbeat,
//! status, error code, the echoed sequence and the active sequence. Fields may not overlap, the
//! payload area is sized for `max_points` points in both directions, and the limits must be
//! representable in the payload type at its resolution, so a map that loads can carry any table
//! within its limits.
//!
//! The documentation numbering of each register (40001, DB100.DBW0, %MB0, %IW0) is computed
//! from the map's `[notation]` and shown beside the PDU address in messages.

use crate::modbus::RegisterKind;
use crate::modbus::codec::{ValueType, WordOrder};
use crate::util::range::Range;
use serde::Deserialize;
use std::fmt;
use std::path::Path;
use thiserror::Error;

/// The generic map (axiscomp's own table protocol at address 0), embedded at build time.
pub const GENERIC_TOML: &str = include_str!("../../plc-maps/cnc/generic.toml");
/// Its path, for messages.
pub const GENERIC_PATH: &str = "plc-maps/cnc/generic.toml";

/// Why a map could not be loaded.
#[derive(Debug, Error)]
pub enum MapError {
    #[error("CNC map {file}: cannot read it: {source}; check the path and permissions")]
    Read {
        file: String,
        source: std::io::Error,
    },
    #[error("CNC map {file}: {message}; fix the key shown (see plc-maps/cnc/generic.toml)")]
    Syntax { file: String, message: String },
    #[error("CNC map {file}: `{key}`: {problem}; {fix}")]
    Invalid {
        file: String,
        key: String,
        problem: String,
        fix: String,
    },
}

impl MapError {
    /// The offending key, for `Invalid` errors.
    pub fn key(&self) -> Option<&str> {
        match self {
            MapError::Invalid { key, .. } => Some(key),
            _ => None,
        }
    }
}

// ---------- raw stage ----------

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMap {
    name: String,
    unit_id: u8,
    notation: RawNotation,
    #[serde(default)]
    defaults: RawDefaults,
    handshake: RawHandshake,
    header: RawHeader,
    payload: RawPayload,
    limits: RawLimits,
    check: Option<RawCheck>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawNotation {
    scheme: String,
    db: Option<u16>,
    first_register: Option<u16>,
    holding_base: Option<u32>,
    input_base: Option<u32>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDefaults {
    word_order: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawField {
    address: u16,
    #[serde(rename = "type")]
    ty: String,
    register: Option<RegisterKind>,
    word_order: Option<String>,
    scale: Option<f64>,
    unit: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHandshake {
    plc_ready: Option<RawField>,
    plc_heartbeat: Option<RawField>,
    status: Option<RawField>,
    error_code: Option<RawField>,
    status_sequence: Option<RawField>,
    active_sequence: Option<RawField>,
    commit: Option<RawField>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCheck {
    request: Option<RawField>,
    answered: Option<RawField>,
    state: Option<RawField>,
    result: Option<RawField>,
    run: Option<RawField>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHeader {
    kind: Option<RawField>,
    axis: Option<RawField>,
    base_axis: Option<RawField>,
    direction: Option<RawField>,
    points: Option<RawField>,
    unit: Option<RawField>,
    start: Option<RawField>,
    interval: Option<RawField>,
    sequence: Option<RawField>,
    crc: Option<RawField>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPayload {
    address: u16,
    #[serde(rename = "type")]
    ty: String,
    word_order: Option<String>,
    scale: f64,
    unit: String,
    sign: String,
    crc_bytes: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLimits {
    max_points: u32,
    max_abs_um: f64,
    max_step_um: f64,
}

// ---------- validated stage ----------

/// Who writes a field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Writer {
    /// axiscomp writes it (push) or serves it read-only (pull).
    Service,
    /// The PLC program writes it (push: the PLC's own registers; pull: the ack range).
    Plc,
}

/// A length unit of a scaled field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LengthUnit {
    Mm,
    Um,
    Nm,
}

impl LengthUnit {
    /// Millimetres per one of this unit.
    pub fn mm(self) -> f64 {
        match self {
            LengthUnit::Mm => 1.0,
            LengthUnit::Um => 1e-3,
            LengthUnit::Nm => 1e-6,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            LengthUnit::Mm => "mm",
            LengthUnit::Um => "um",
            LengthUnit::Nm => "nm",
        }
    }

    fn parse(s: &str) -> Option<LengthUnit> {
        match s {
            "mm" => Some(LengthUnit::Mm),
            "um" | "µm" => Some(LengthUnit::Um),
            "nm" => Some(LengthUnit::Nm),
            _ => None,
        }
    }
}

/// How the PLC's documentation numbers registers (for messages and listings only).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Notation {
    /// Modbus reference numbers: holding register `a` is 4xxxx (`40001 + a`), input 3xxxx.
    Modbus,
    /// Siemens S7 with MB_SERVER: holding register `a` is `DB<db>.DBW<2·(a − first)>` of the
    /// data block given as MB_HOLD_REG (DBD for 32-bit fields); input register `a` is `IW<2a>`.
    S7Db { db: u16, first_register: u16 },
    /// Beckhoff TwinCAT Modbus TCP server, default mapping: holding register `a` in
    /// 0x3000..=0x5FFF is `%MB<2·(a − 0x3000)>` (PLC memory area, ADS index group 0x4020);
    /// input register `a` is `%IB<2a>` (physical inputs).
    TwinCat,
    /// CODESYS Modbus TCP server device: holding register `a` is `%IW<holding_base + a>`,
    /// input register `a` is `%QW<input_base + a>` (word-indexed; the bases are where the
    /// project's I/O mapping puts the device).
    Codesys { holding_base: u32, input_base: u32 },
}

/// The first and last holding register of TwinCAT's default %MB mapping.
pub const TWINCAT_MB_FIRST: u16 = 0x3000;
pub const TWINCAT_MB_LAST: u16 = 0x5FFF;

impl Notation {
    /// The documentation name of register `address` of `kind`, for a value of `words`
    /// registers.
    pub fn name(&self, kind: RegisterKind, address: u16, words: u16) -> String {
        let a = address as u32;
        match (self, kind) {
            (Notation::Modbus, RegisterKind::Holding) => modbus_ref(4, a),
            (Notation::Modbus, RegisterKind::Input) => modbus_ref(3, a),
            (Notation::S7Db { db, first_register }, RegisterKind::Holding) => {
                let byte = 2 * a.saturating_sub(*first_register as u32);
                let w = if words == 2 { "DBD" } else { "DBW" };
                format!("DB{db}.{w}{byte}")
            }
            (Notation::S7Db { .. }, RegisterKind::Input) => {
                let w = if words == 2 { "ID" } else { "IW" };
                format!("{w}{}", 2 * a)
            }
            (Notation::TwinCat, RegisterKind::Holding) => {
                format!("%MB{}", 2 * a.saturating_sub(TWINCAT_MB_FIRST as u32))
            }
            (Notation::TwinCat, RegisterKind::Input) => format!("%IB{}", 2 * a),
            (Notation::Codesys { holding_base, .. }, RegisterKind::Holding) => {
                format!("%IW{}", holding_base + a)
            }
            (Notation::Codesys { input_base, .. }, RegisterKind::Input) => {
                format!("%QW{}", input_base + a)
            }
        }
    }
}

fn modbus_ref(prefix: u32, a: u32) -> String {
    // Five digits while they suffice (40001..49999), the six-digit form beyond.
    if a < 9999 {
        format!("{prefix}{:04}", a + 1)
    } else {
        format!("{prefix}{:05}", a + 1)
    }
}

/// One field of the map.
#[derive(Clone, Debug, PartialEq)]
pub struct Field {
    /// Its key, e.g. `header.start`.
    pub key: &'static str,
    pub kind: RegisterKind,
    /// 0-based PDU address of its first register.
    pub address: u16,
    pub ty: ValueType,
    pub order: WordOrder,
    /// Millimetres per count for lengths (start, interval); 1 for codes and counters.
    pub mm_per_count: f64,
    pub writer: Writer,
}

impl Field {
    /// Registers it occupies.
    pub fn words(&self) -> u16 {
        self.ty.words()
    }
    /// One past its last register.
    pub fn end(&self) -> u32 {
        self.address as u32 + self.words() as u32
    }
}

/// The handshake fields.
#[derive(Clone, Debug, PartialEq)]
pub struct Handshake {
    /// 1 while the PLC accepts a table (PLC → service).
    pub plc_ready: Field,
    /// A counter the PLC increments (PLC → service).
    pub plc_heartbeat: Field,
    /// 0 idle, 1 busy, 2 accepted, 3 rejected (PLC → service).
    pub status: Field,
    /// Why the last commit was rejected; 0 when accepted (PLC → service).
    pub error_code: Field,
    /// The sequence the status refers to: the PLC echoes the committed sequence here.
    pub status_sequence: Field,
    /// The sequence of the table the PLC applies now (0: none).
    pub active_sequence: Field,
    /// Written last by the service: the new sequence, meaning "the staged table is complete".
    pub commit: Field,
}

impl Handshake {
    /// The fields the PLC writes, in a fixed order.
    pub fn plc_fields(&self) -> [&Field; 6] {
        [
            &self.plc_ready,
            &self.plc_heartbeat,
            &self.status,
            &self.error_code,
            &self.status_sequence,
            &self.active_sequence,
        ]
    }
}

/// The check handshake's fields (`[check]`, optional): the PLC asks for a short check of the
/// axis in a break, the service answers (`plc::check`).
#[derive(Clone, Debug, PartialEq)]
pub struct CheckFields {
    /// A new nonzero value asks for a check (PLC → service).
    pub request: Field,
    /// The request the state and result are for (service → PLC).
    pub answered: Field,
    /// 0 idle, 1 busy, 2 done, 3 refused (service → PLC).
    pub state: Field,
    /// What the check found, or why it was refused (service → PLC; `plc::check::CheckResult`).
    pub result: Field,
    /// The stored run the check is (service → PLC; 0 none).
    pub run: Field,
}

impl CheckFields {
    /// Every field, the PLC's first.
    pub fn fields(&self) -> [&Field; 5] {
        [
            &self.request,
            &self.answered,
            &self.state,
            &self.result,
            &self.run,
        ]
    }
}

/// The table header fields (written by the service).
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub kind: Field,
    pub axis: Field,
    pub base_axis: Field,
    pub direction: Field,
    pub points: Field,
    pub unit: Field,
    pub start: Field,
    pub interval: Field,
    pub sequence: Field,
    pub crc: Field,
}

impl Header {
    /// All header fields, in a fixed order.
    pub fn fields(&self) -> [&Field; 10] {
        [
            &self.kind,
            &self.axis,
            &self.base_axis,
            &self.direction,
            &self.points,
            &self.unit,
            &self.start,
            &self.interval,
            &self.sequence,
            &self.crc,
        ]
    }
}

/// The sign of the payload values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sign {
    /// The correction the controller adds to the commanded position: `−(measured − nominal)`.
    Correction,
    /// The error as measured: `measured − nominal`.
    Error,
}

/// Byte order of the payload values fed to the CRC.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CrcBytes {
    /// Each value's two's-complement bytes, most significant first (an S7 DB's memory image).
    BigEndian,
    /// Least significant first (the memory image of a DINT array on x86/ARM PLCs).
    LittleEndian,
}

/// The payload: one value per point (and direction), from `address` on.
#[derive(Clone, Debug, PartialEq)]
pub struct Payload {
    pub address: u16,
    /// `i16` or `i32`.
    pub ty: ValueType,
    pub order: WordOrder,
    /// Resolution: millimetres per count.
    pub mm_per_count: f64,
    /// The resolution in nanometres per count (the header's `unit` value).
    pub unit_nm: u16,
    pub sign: Sign,
    pub crc_bytes: CrcBytes,
    /// Registers reserved: room for `max_points` points in both directions.
    pub capacity: u32,
}

impl Payload {
    /// One past the last reserved register.
    pub fn end(&self) -> u32 {
        self.address as u32 + self.capacity
    }
}

/// What the PLC accepts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Most points per direction profile (at least 2).
    pub max_points: u16,
    /// Largest |value| (mm).
    pub max_abs_mm: f64,
    /// Largest change between neighbouring points (mm).
    pub max_step_mm: f64,
}

/// A validated CNC map.
#[derive(Clone, Debug, PartialEq)]
pub struct CncMap {
    /// The file it came from (for messages).
    pub file: String,
    pub name: String,
    pub unit_id: u8,
    pub notation: Notation,
    pub handshake: Handshake,
    pub header: Header,
    pub payload: Payload,
    pub limits: Limits,
    /// The check handshake, when the map has one.
    pub check: Option<CheckFields>,
}

/// A field as a listing shows it.
#[derive(Clone, Debug, PartialEq)]
pub struct FieldDoc {
    pub key: String,
    pub kind: RegisterKind,
    pub address: u16,
    pub words: u16,
    pub doc: String,
    pub ty: ValueType,
    pub order: WordOrder,
    pub writer: Writer,
}

impl fmt::Display for FieldDoc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{:<26} {:<7} {:>5} ({}) {} {} {}",
            self.key,
            self.kind,
            self.address,
            self.doc,
            self.ty,
            self.order,
            match self.writer {
                Writer::Service => "written by axiscomp",
                Writer::Plc => "written by the PLC",
            }
        )
    }
}

impl CncMap {
    /// Load and validate a map file.
    pub fn load(path: &Path) -> Result<CncMap, MapError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| MapError::Read {
            file: file.clone(),
            source,
        })?;
        CncMap::parse(&text, &file)
    }

    /// The built-in generic map (axiscomp's own table protocol at address 0).
    pub fn generic() -> Result<CncMap, MapError> {
        CncMap::parse(GENERIC_TOML, GENERIC_PATH)
    }

    /// Parse and validate map text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<CncMap, MapError> {
        let raw: RawMap = toml::from_str(text).map_err(|e| MapError::Syntax {
            file: file.to_string(),
            message: e.to_string().trim().replace('\n', " "),
        })?;
        validate(raw, &Ctx { file })
    }

    /// The documentation name of a field's first register.
    pub fn doc(&self, field: &Field) -> String {
        self.notation.name(field.kind, field.address, field.words())
    }

    /// The documentation name of holding register `address`.
    pub fn doc_holding(&self, address: u16) -> String {
        self.notation.name(RegisterKind::Holding, address, 1)
    }

    /// Every field (handshake, header, then the payload area), for listings and checks.
    pub fn describe(&self) -> Vec<FieldDoc> {
        let mut out: Vec<FieldDoc> = self
            .handshake
            .plc_fields()
            .into_iter()
            .chain([&self.handshake.commit])
            .chain(self.header.fields())
            .chain(self.check.iter().flat_map(CheckFields::fields))
            .map(|f| FieldDoc {
                key: f.key.to_string(),
                kind: f.kind,
                address: f.address,
                words: f.words(),
                doc: self.doc(f),
                ty: f.ty,
                order: f.order,
                writer: f.writer,
            })
            .collect();
        out.push(FieldDoc {
            key: format!(
                "payload[0..{}]",
                self.payload.capacity / self.payload.ty.words() as u32
            ),
            kind: RegisterKind::Holding,
            address: self.payload.address,
            words: u16::try_from(self.payload.capacity).unwrap_or(u16::MAX),
            doc: self.doc_holding(self.payload.address),
            ty: self.payload.ty,
            order: self.payload.order,
            writer: Writer::Service,
        });
        out
    }

    /// The register span (start, end) of the holding registers the pull server serves: from
    /// the lowest to one past the highest register of any field or the payload area.
    pub fn holding_span(&self) -> (u16, u32) {
        let mut lo = self.payload.address as u32;
        let mut hi = self.payload.end();
        for f in self
            .handshake
            .plc_fields()
            .into_iter()
            .chain([&self.handshake.commit])
            .chain(self.header.fields())
            .chain(self.check.iter().flat_map(CheckFields::fields))
            .filter(|f| f.kind == RegisterKind::Holding)
        {
            lo = lo.min(f.address as u32);
            hi = hi.max(f.end());
        }
        (lo as u16, hi)
    }
}

struct Ctx<'a> {
    file: &'a str,
}

impl Ctx<'_> {
    fn err(&self, key: impl Into<String>, problem: impl Into<String>, fix: &str) -> MapError {
        MapError::Invalid {
            file: self.file.to_string(),
            key: key.into(),
            problem: problem.into(),
            fix: fix.to_string(),
        }
    }
}

fn order(s: Option<&str>, default: WordOrder, key: &str, cx: &Ctx) -> Result<WordOrder, MapError> {
    match s {
        Some(s) => s.parse().map_err(|e: String| {
            cx.err(
                key,
                e,
                "ABCD = big-endian words (Modbus, S7), CDAB = low word first (x86/ARM PLCs)",
            )
        }),
        None => Ok(default),
    }
}

/// What a field may be.
#[derive(Clone, Copy)]
enum Shape {
    /// A 16-bit code or counter.
    Code,
    /// A sequence number: u16 or u32 (all sequence fields alike).
    Sequence,
    /// CRC-32.
    Crc,
    /// A length: i32 or f32 with a scale and unit.
    Length,
}

fn field(
    raw: Option<RawField>,
    key: &'static str,
    shape: Shape,
    writer: Writer,
    default_order: WordOrder,
    cx: &Ctx,
) -> Result<Field, MapError> {
    let r = raw.ok_or_else(|| {
        cx.err(
            key,
            "missing",
            "give it as { address = <0-based register>, type = \"...\" } (see plc-maps/README.md)",
        )
    })?;
    let ty: ValueType =
        r.ty.parse()
            .map_err(|e: String| cx.err(format!("{key}.type"), e, "fix the type"))?;
    let (allowed, what): (&[ValueType], &str) = match shape {
        Shape::Code => (&[ValueType::U16], "u16"),
        Shape::Sequence => (&[ValueType::U16, ValueType::U32], "u16 or u32"),
        Shape::Crc => (&[ValueType::U32], "u32"),
        Shape::Length => (&[ValueType::I32, ValueType::F32], "i32 or f32"),
    };
    if !allowed.contains(&ty) {
        return Err(cx.err(
            format!("{key}.type"),
            format!("{ty} is not allowed here"),
            &format!("use {what}"),
        ));
    }
    let kind = r.register.unwrap_or(RegisterKind::Holding);
    if writer == Writer::Service && kind == RegisterKind::Input {
        return Err(cx.err(
            format!("{key}.register"),
            "axiscomp writes this field, and input registers cannot be written",
            "use register = \"holding\" (or leave it out)",
        ));
    }
    if r.address as u32 + ty.words() as u32 > 0x1_0000 {
        return Err(cx.err(
            format!("{key}.address"),
            format!("{} ({ty}) runs past the last register 65535", r.address),
            "use a lower address",
        ));
    }
    let order = order(
        r.word_order.as_deref(),
        default_order,
        &format!("{key}.word_order"),
        cx,
    )?;
    let mm_per_count = match shape {
        Shape::Length => {
            let scale = r.scale.ok_or_else(|| {
                cx.err(
                    format!("{key}.scale"),
                    "missing",
                    "give scale (units per count) and unit, e.g. scale = 0.1, unit = \"um\"",
                )
            })?;
            let unit = r.unit.as_deref().unwrap_or("");
            let unit = LengthUnit::parse(unit).ok_or_else(|| {
                cx.err(
                    format!("{key}.unit"),
                    format!("unknown length unit {unit:?}"),
                    "use \"mm\", \"um\" or \"nm\"",
                )
            })?;
            // From a nanometre to a millimetre per count.
            let mm = scale * unit.mm();
            if !Range::new(1e-6, 1.0, "mm").contains(mm) {
                return Err(cx.err(
                    format!("{key}.scale"),
                    format!(
                        "{} {} per count is out of range: use 1 nm to 1 mm per count",
                        crate::util::range::num(scale),
                        unit.name()
                    ),
                    "give the units per count, e.g. scale = 0.1, unit = \"um\"",
                ));
            }
            mm
        }
        _ => {
            for (k, present) in [("scale", r.scale.is_some()), ("unit", r.unit.is_some())] {
                if present {
                    return Err(cx.err(
                        format!("{key}.{k}"),
                        "this field is a code or counter, not a length",
                        "remove it",
                    ));
                }
            }
            1.0
        }
    };
    Ok(Field {
        key,
        kind,
        address: r.address,
        ty,
        order,
        mm_per_count,
        writer,
    })
}

fn notation(raw: RawNotation, cx: &Ctx) -> Result<Notation, MapError> {
    let extra = |keys: &[(&str, bool)], scheme: &str| -> Result<(), MapError> {
        match keys.iter().find(|(_, present)| *present) {
            Some((k, _)) => Err(cx.err(
                format!("notation.{k}"),
                format!("not a key of scheme \"{scheme}\""),
                "remove it",
            )),
            None => Ok(()),
        }
    };
    let (db, first, hb, ib) = (
        raw.db.is_some(),
        raw.first_register.is_some(),
        raw.holding_base.is_some(),
        raw.input_base.is_some(),
    );
    match raw.scheme.as_str() {
        "modbus" => {
            extra(
                &[
                    ("db", db),
                    ("first_register", first),
                    ("holding_base", hb),
                    ("input_base", ib),
                ],
                "modbus",
            )?;
            Ok(Notation::Modbus)
        }
        "s7-db" => {
            extra(&[("holding_base", hb), ("input_base", ib)], "s7-db")?;
            let db = raw.db.ok_or_else(|| {
                cx.err(
                    "notation.db",
                    "missing",
                    "give the number of the data block passed as MB_HOLD_REG",
                )
            })?;
            Ok(Notation::S7Db {
                db,
                first_register: raw.first_register.unwrap_or(0),
            })
        }
        "twincat" => {
            extra(
                &[
                    ("db", db),
                    ("first_register", first),
                    ("holding_base", hb),
                    ("input_base", ib),
                ],
                "twincat",
            )?;
            Ok(Notation::TwinCat)
        }
        "codesys" => {
            extra(&[("db", db), ("first_register", first)], "codesys")?;
            Ok(Notation::Codesys {
                holding_base: raw.holding_base.unwrap_or(0),
                input_base: raw.input_base.unwrap_or(0),
            })
        }
        other => Err(cx.err(
            "notation.scheme",
            format!("unknown scheme {other:?}"),
            "use \"modbus\", \"s7-db\", \"twincat\" or \"codesys\"",
        )),
    }
}

fn validate(raw: RawMap, cx: &Ctx) -> Result<CncMap, MapError> {
    if raw.name.trim().is_empty() {
        return Err(cx.err(
            "name",
            "empty",
            "name the PLC (it is stored with every publication)",
        ));
    }
    let notation = notation(raw.notation, cx)?;
    let dflt = order(
        raw.defaults.word_order.as_deref(),
        WordOrder::Abcd,
        "defaults.word_order",
        cx,
    )?;
    let h = raw.handshake;
    use Shape::*;
    use Writer::*;
    let handshake = Handshake {
        plc_ready: field(h.plc_ready, "handshake.plc_ready", Code, Plc, dflt, cx)?,
        plc_heartbeat: field(
            h.plc_heartbeat,
            "handshake.plc_heartbeat",
            Code,
            Plc,
            dflt,
            cx,
        )?,
        status: field(h.status, "handshake.status", Code, Plc, dflt, cx)?,
        error_code: field(h.error_code, "handshake.error_code", Code, Plc, dflt, cx)?,
        status_sequence: field(
            h.status_sequence,
            "handshake.status_sequence",
            Sequence,
            Plc,
            dflt,
            cx,
        )?,
        active_sequence: field(
            h.active_sequence,
            "handshake.active_sequence",
            Sequence,
            Plc,
            dflt,
            cx,
        )?,
        commit: field(h.commit, "handshake.commit", Sequence, Service, dflt, cx)?,
    };
    let r = raw.header;
    let header = Header {
        kind: field(r.kind, "header.kind", Code, Service, dflt, cx)?,
        axis: field(r.axis, "header.axis", Code, Service, dflt, cx)?,
        base_axis: field(r.base_axis, "header.base_axis", Code, Service, dflt, cx)?,
        direction: field(r.direction, "header.direction", Code, Service, dflt, cx)?,
        points: field(r.points, "header.points", Code, Service, dflt, cx)?,
        unit: field(r.unit, "header.unit", Code, Service, dflt, cx)?,
        start: field(r.start, "header.start", Length, Service, dflt, cx)?,
        interval: field(r.interval, "header.interval", Length, Service, dflt, cx)?,
        sequence: field(r.sequence, "header.sequence", Sequence, Service, dflt, cx)?,
        crc: field(r.crc, "header.crc", Crc, Service, dflt, cx)?,
    };
    // One sequence type for all four, so every sequence the service sends can be echoed.
    let seq_ty = header.sequence.ty;
    for f in [
        &handshake.commit,
        &handshake.status_sequence,
        &handshake.active_sequence,
    ] {
        if f.ty != seq_ty {
            return Err(cx.err(
                format!("{}.type", f.key),
                format!("{} but header.sequence is {seq_ty}", f.ty),
                "give the four sequence fields one type (u32 unless the PLC lacks 32-bit words)",
            ));
        }
    }

    // Limits and payload.
    let l = raw.limits;
    if !(2..=u16::MAX as u32).contains(&l.max_points) {
        return Err(cx.err(
            "limits.max_points",
            format!("{} points", l.max_points),
            "give 2 to 65535 (the PLC's table size)",
        ));
    }
    // A compensation value or step from a nanometre to 10 mm: beyond it the machine needs
    // repair, not compensation.
    for (k, v) in [("max_abs_um", l.max_abs_um), ("max_step_um", l.max_step_um)] {
        Range::new(0.001, 10_000.0, "µm").check(v).map_err(|p| {
            cx.err(
                format!("limits.{k}"),
                p,
                "give the largest value the PLC accepts, in µm",
            )
        })?;
    }
    let limits = Limits {
        max_points: l.max_points as u16,
        max_abs_mm: l.max_abs_um * 1e-3,
        max_step_mm: l.max_step_um * 1e-3,
    };
    let p = raw.payload;
    let ty: ValueType =
        p.ty.parse()
            .map_err(|e: String| cx.err("payload.type", e, "use i32 (or i16)"))?;
    if !matches!(ty, ValueType::I16 | ValueType::I32) {
        return Err(cx.err(
            "payload.type",
            format!("{ty} is not allowed for the payload"),
            "use i32 (or i16 for a PLC with 16-bit tables); the CRC runs over integer values",
        ));
    }
    let porder = order(p.word_order.as_deref(), dflt, "payload.word_order", cx)?;
    let unit = LengthUnit::parse(&p.unit).ok_or_else(|| {
        cx.err(
            "payload.unit",
            format!("unknown length unit {:?}", p.unit),
            "use \"mm\", \"um\" or \"nm\"",
        )
    })?;
    if !(p.scale.is_finite() && p.scale > 0.0) {
        return Err(cx.err(
            "payload.scale",
            format!("{} is not a positive number", p.scale),
            "give the resolution in units per count, e.g. scale = 0.1, unit = \"um\"",
        ));
    }
    let mm_per_count = p.scale * unit.mm();
    let nm = mm_per_count * 1e6;
    if (nm - nm.round()).abs() > 1e-6 || !(1.0..=65535.0).contains(&nm.round()) {
        return Err(cx.err(
            "payload.scale",
            format!("{} {} is {nm} nm per count", p.scale, unit.name()),
            "the header's unit field carries the resolution in whole nanometres (1 to 65535): use e.g. 0.1 um or 1 um",
        ));
    }
    let sign = match p.sign.as_str() {
        "correction" => Sign::Correction,
        "error" => Sign::Error,
        other => {
            return Err(cx.err(
                "payload.sign",
                format!("unknown sign {other:?}"),
                "use \"correction\" (value = −(measured − nominal), what the controller adds) or \"error\" (measured − nominal)",
            ));
        }
    };
    let crc_bytes = match p.crc_bytes.as_str() {
        "big-endian" => CrcBytes::BigEndian,
        "little-endian" => CrcBytes::LittleEndian,
        other => {
            return Err(cx.err(
                "payload.crc_bytes",
                format!("unknown byte order {other:?}"),
                "use \"big-endian\" (S7 memory image) or \"little-endian\" (x86/ARM PLC memory image)",
            ));
        }
    };
    let max_counts = limits.max_abs_mm / mm_per_count;
    let (_, type_max) = ty.range();
    if max_counts > type_max {
        return Err(cx.err(
            "limits.max_abs_um",
            format!(
                "{} µm is {max_counts:.0} counts at {nm:.0} nm per count, more than {ty} holds ({type_max})",
                l.max_abs_um
            ),
            "lower max_abs_um, coarsen payload.scale or use an i32 payload",
        ));
    }
    let capacity = 2 * limits.max_points as u32 * ty.words() as u32;
    if p.address as u32 + capacity > 0x1_0000 {
        return Err(cx.err(
            "limits.max_points",
            format!(
                "{} points in both directions need {capacity} registers from {}, past register 65535",
                limits.max_points, p.address
            ),
            "lower max_points or move the payload",
        ));
    }
    let payload = Payload {
        address: p.address,
        ty,
        order: porder,
        mm_per_count,
        unit_nm: nm.round() as u16,
        sign,
        crc_bytes,
        capacity,
    };

    // No two fields (or a field and the payload area) share a register of the same table.
    let check = match raw.check {
        Some(c) => Some(CheckFields {
            request: field(c.request, "check.request", Sequence, Plc, dflt, cx)?,
            answered: field(c.answered, "check.answered", Sequence, Service, dflt, cx)?,
            state: field(c.state, "check.state", Code, Service, dflt, cx)?,
            result: field(c.result, "check.result", Code, Service, dflt, cx)?,
            run: field(c.run, "check.run", Sequence, Service, dflt, cx)?,
        }),
        None => None,
    };
    if let Some(c) = &check
        && c.request.ty != c.answered.ty
    {
        return Err(cx.err(
            "check.answered.type",
            format!(
                "{} while check.request is {}: the service echoes the request",
                c.answered.ty, c.request.ty
            ),
            "give both the same type",
        ));
    }
    let mut spans: Vec<(RegisterKind, u32, u32, String)> = handshake
        .plc_fields()
        .into_iter()
        .chain([&handshake.commit])
        .chain(header.fields())
        .chain(check.iter().flat_map(CheckFields::fields))
        .map(|f| (f.kind, f.address as u32, f.end(), f.key.to_string()))
        .collect();
    spans.push((
        RegisterKind::Holding,
        payload.address as u32,
        payload.end(),
        "payload".into(),
    ));
    for (i, a) in spans.iter().enumerate() {
        for b in &spans[..i] {
            if a.0 == b.0 && a.1 < b.2 && b.1 < a.2 {
                let key = if a.3 == "payload" {
                    "payload.address".to_string()
                } else {
                    format!("{}.address", a.3)
                };
                return Err(cx.err(
                    key,
                    format!(
                        "{} registers {}..{} overlap {} ({}..{})",
                        a.0, a.1, a.2, b.3, b.1, b.2
                    ),
                    "give every field its own registers (the payload reserves 2 × max_points values)",
                ));
            }
        }
    }
    // TwinCAT's default mapping puts the PLC memory area at 0x3000..=0x5FFF only.
    if notation == Notation::TwinCat {
        for (kind, lo, hi, key) in &spans {
            if *kind == RegisterKind::Holding
                && (*lo < TWINCAT_MB_FIRST as u32 || *hi > TWINCAT_MB_LAST as u32 + 1)
            {
                let key = if key == "payload" {
                    "payload.address".to_string()
                } else {
                    format!("{key}.address")
                };
                return Err(cx.err(
                    key,
                    format!(
                        "registers {lo}..{hi} lie outside TwinCAT's default %MB mapping 0x3000 to 0x5FFF"
                    ),
                    "move it into 0x3000 to 0x5FFF (12288 to 24575), or change the server's mapping and use notation scheme \"modbus\"",
                ));
            }
        }
    }
    if let Notation::S7Db { first_register, .. } = notation {
        for (kind, lo, _, key) in &spans {
            if *kind == RegisterKind::Holding && *lo < first_register as u32 {
                return Err(cx.err(
                    format!("{key}.address"),
                    format!("register {lo} lies below notation.first_register {first_register} (HR_Start_Offset)"),
                    "MB_SERVER answers only from HR_Start_Offset on: move the field or lower first_register",
                ));
            }
        }
    }
    Ok(CncMap {
        file: cx.file.to_string(),
        name: raw.name,
        unit_id: raw.unit_id,
        notation,
        handshake,
        header,
        payload,
        limits,
        check,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn maps_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc")
    }

    fn fixtures() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/cnc-maps")
    }

    #[test]
    fn shipped_maps_are_valid() {
        let mut names = Vec::new();
        for e in std::fs::read_dir(maps_dir()).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                let m = CncMap::load(&p).unwrap_or_else(|e| panic!("{e}"));
                assert!(m.limits.max_points >= 256, "{}", p.display());
                names.push(p.file_name().unwrap().to_string_lossy().into_owned());
            }
        }
        names.sort();
        assert_eq!(
            names,
            [
                "beckhoff-twincat.toml",
                "codesys.toml",
                "generic.toml",
                "siemens-s7-1500.toml"
            ]
        );
    }

    #[test]
    fn generic_layout_and_notation() {
        let m = CncMap::generic().unwrap();
        assert_eq!(m.unit_id, 1);
        assert_eq!(m.notation, Notation::Modbus);
        let h = &m.handshake;
        assert_eq!(
            (
                h.plc_ready.address,
                h.plc_heartbeat.address,
                h.status.address,
                h.error_code.address,
                h.status_sequence.address,
                h.active_sequence.address,
                h.commit.address
            ),
            (0, 1, 2, 3, 4, 6, 8)
        );
        assert_eq!(m.header.kind.address, 16);
        assert_eq!(m.header.crc.address, 28);
        assert_eq!(m.header.crc.ty, ValueType::U32);
        assert_eq!(m.payload.address, 32);
        assert_eq!(m.payload.unit_nm, 100);
        assert!((m.payload.mm_per_count - 1e-4).abs() < 1e-18);
        assert!((m.header.start.mm_per_count - 1e-4).abs() < 1e-18);
        assert_eq!(m.payload.capacity, 2 * 1024 * 2);
        assert_eq!(m.doc(&m.handshake.plc_ready), "40001");
        assert_eq!(m.doc(&m.header.crc), "40029");
        assert_eq!(m.holding_span(), (0, 32 + 4096));
        let d = m.describe();
        // 6 PLC handshake fields, commit, 10 header fields, 5 check fields, the payload.
        assert_eq!(d.len(), 23);
        assert!(d[0].to_string().contains("40001"), "{}", d[0]);
        let c = m
            .check
            .as_ref()
            .expect("the generic map has the check fields");
        assert_eq!(
            c.fields().map(|f| (f.address, f.writer)),
            [
                (10, Writer::Plc),
                (11, Writer::Service),
                (12, Writer::Service),
                (13, Writer::Service),
                (14, Writer::Service)
            ]
        );
        assert_eq!(m.doc(&c.run), "40015");
    }

    #[test]
    fn a_check_section_is_checked_like_the_rest() {
        let g = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc/generic.toml"),
        )
        .expect("the generic map");
        // The check's request over the handshake's commit; an answer of another type than
        // the request; a state the service writes in an input register.
        for (from, to, key) in [
            (
                "request  = { address = 10,",
                "request  = { address = 9,",
                "check.request.address",
            ),
            (
                "answered = { address = 11, type = \"u16\" }",
                "answered = { address = 11, type = \"u32\" }",
                "check.answered",
            ),
            (
                "state    = { address = 12, type = \"u16\" }",
                "state    = { address = 12, type = \"u16\", register = \"input\" }",
                "check.state.register",
            ),
        ] {
            assert!(g.contains(from), "{from}");
            let e = CncMap::parse(&g.replace(from, to), "generic.toml").unwrap_err();
            assert!(e.key().is_some_and(|k| k.starts_with(key)), "{key}: {e}");
        }
        // Without the section a map has no check.
        let start = g.find("[check]").expect("section");
        let end = g.find("[header]").expect("header");
        let none = format!("{}{}", &g[..start], &g[end..]);
        assert_eq!(CncMap::parse(&none, "x.toml").expect("valid").check, None);
    }

    #[test]
    fn notations_name_registers_as_the_vendors_do() {
        use RegisterKind::*;
        assert_eq!(Notation::Modbus.name(Holding, 0, 1), "40001");
        assert_eq!(Notation::Modbus.name(Holding, 9998, 1), "49999");
        assert_eq!(Notation::Modbus.name(Holding, 9999, 1), "410000");
        assert_eq!(Notation::Modbus.name(Input, 4, 1), "30005");
        let s7 = Notation::S7Db {
            db: 100,
            first_register: 0,
        };
        assert_eq!(s7.name(Holding, 0, 1), "DB100.DBW0");
        assert_eq!(s7.name(Holding, 22, 2), "DB100.DBD44");
        assert_eq!(s7.name(Input, 3, 1), "IW6");
        assert_eq!(Notation::TwinCat.name(Holding, 0x3000, 1), "%MB0");
        assert_eq!(Notation::TwinCat.name(Holding, 0x3010, 2), "%MB32");
        let cds = Notation::Codesys {
            holding_base: 0,
            input_base: 10,
        };
        assert_eq!(cds.name(Holding, 16, 1), "%IW16");
        assert_eq!(cds.name(Input, 2, 1), "%QW12");
    }

    /// Every invalid fixture fails naming its file and the key it was written to test.
    #[test]
    fn invalid_fixtures_name_file_and_key() {
        let cases: [(&str, &str); 22] = [
            ("empty-name.toml", "name"),
            ("missing-crc.toml", "header.crc"),
            ("bad-type.toml", "header.kind.type"),
            ("crc-not-u32.toml", "header.crc.type"),
            ("length-as-u16.toml", "header.start.type"),
            (
                "bad-word-order.toml",
                "handshake.status_sequence.word_order",
            ),
            (
                "commit-in-input-registers.toml",
                "handshake.commit.register",
            ),
            ("field-past-end.toml", "header.crc.address"),
            ("overlap.toml", "header.points.address"),
            ("payload-overlaps-header.toml", "payload.address"),
            ("sequence-types-differ.toml", "handshake.commit.type"),
            ("missing-scale.toml", "header.interval.scale"),
            ("scale-on-code.toml", "header.direction.scale"),
            ("bad-length-unit.toml", "header.start.unit"),
            ("payload-f32.toml", "payload.type"),
            ("payload-scale-not-nm.toml", "payload.scale"),
            ("bad-sign.toml", "payload.sign"),
            ("bad-crc-bytes.toml", "payload.crc_bytes"),
            ("max-points-one.toml", "limits.max_points"),
            ("max-abs-too-big-for-i16.toml", "limits.max_abs_um"),
            ("twincat-outside-mb.toml", "handshake.plc_ready.address"),
            ("bad-notation.toml", "notation.scheme"),
        ];
        for (file, key) in cases {
            let path = fixtures().join(file);
            let err = CncMap::load(&path).expect_err(file);
            let msg = err.to_string();
            assert_eq!(err.key(), Some(key), "{file}: {msg}");
            assert!(msg.contains(file), "{msg}");
            assert!(msg.contains(&format!("`{key}`")), "{msg}");
        }
    }

    #[test]
    fn syntax_errors_name_file_and_field() {
        for (file, word) in [
            ("unknown-key.toml", "max_point"),
            ("unknown-field-key.toml", "offset"),
            ("unit-id-too-big.toml", "unit_id"),
            ("bad-register-kind.toml", "register"),
        ] {
            let err = CncMap::load(&fixtures().join(file)).expect_err(file);
            assert!(matches!(err, MapError::Syntax { .. }), "{file}: {err}");
            let msg = err.to_string();
            assert!(msg.contains(file) && msg.contains(word), "{file}: {msg}");
        }
        let err = CncMap::load(&fixtures().join("no-such-file.toml")).unwrap_err();
        assert!(matches!(err, MapError::Read { .. }));
        assert!(err.to_string().contains("no-such-file.toml"));
    }
}
