//! I/O-module maps (`plc-maps/io/*.toml`, DESIGN §6): which registers hold the PSD signals and
//! how counts become volts and volts become a spot. Two stages, as everywhere: the raw TOML
//! (serde, `deny_unknown_fields`), then a validated [`IoMap`]. Every error names the file, the
//! key and what to do.
//!
//! One block read per frame: the map names one register block (input or holding registers,
//! unit id, 0-based start, 1..=125 registers) and every channel is an offset into it, so the
//! six readings of a frame are one snapshot of the module.
//!
//! Channel modes (the whole map uses one):
//! - `conditioned`: a PSD signal processor delivers X, Y and SUM voltages per PSD;
//!   `x = gain_x_mm_per_v · V_X + offset_x_mm` (same for y).
//! - `electrodes`: the module digitises the four electrode signals of each PSD (X1, X2, Y1, Y2,
//!   after transimpedance amplifiers, so proportional to the photocurrents). Hamamatsu, "PSD
//!   (position sensitive detector) — technical information", §3 two-dimensional PSDs:
//!   duo-lateral, formulas (3-1)/(3-2), `2x/Lx = (I_X2 − I_X1)/(I_X1 + I_X2)` and
//!   `2y/Ly = (I_Y2 − I_Y1)/(I_Y1 + I_Y2)`; tetra-lateral, formulas (3-3)/(3-4), "the same as
//!   for the duo-lateral type". `L` is the active length along the axis (electrode to
//!   electrode). The pin-cushion (improved tetra-lateral) type uses different formulas,
//!   (3-5)/(3-6), and is not supported here. SUM is the sum of the four electrode signals (for a
//!   duo-lateral PSD that is twice the photocurrent, as each layer carries all of it).
//!
//! A PSD whose SUM is below `sum_threshold_v` has no spot (beam blocked or off the PSD).
//!
//! Counts to volts per channel: `V = counts · volts_per_count + volts_offset`, after clearing
//! `status_bits` low bits of a 16-bit integer (modules that put diagnostics there).

use super::super::modbus::RegisterKind;
use super::super::modbus::codec::{self, CodecError, ReadRange, ValueType, WordOrder};
use crate::util::range::Range;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;
use thiserror::Error;

/// The map the twin serves by default (`plc-maps/io/generic.toml`, embedded at build time).
pub const GENERIC_TOML: &str = include_str!("../../plc-maps/io/generic.toml");
/// Its path, for messages.
pub const GENERIC_PATH: &str = "plc-maps/io/generic.toml";

/// Why a map could not be loaded.
#[derive(Debug, Error)]
pub enum MapError {
    #[error("I/O map {file}: cannot read it: {source}; check the path and permissions")]
    Read {
        file: String,
        source: std::io::Error,
    },
    #[error("I/O map {file}: {message}; fix the key shown (see plc-maps/io/generic.toml)")]
    Syntax { file: String, message: String },
    #[error("I/O map {file}: `{key}`: {problem}; {fix}")]
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
    register: RegisterKind,
    unit_id: u8,
    block_start: u16,
    block_length: u16,
    mode: String,
    sum_threshold_v: f64,
    #[serde(default)]
    defaults: RawDefaults,
    #[serde(default)]
    psd: Vec<RawPsd>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDefaults {
    #[serde(rename = "type")]
    ty: Option<String>,
    word_order: Option<String>,
    volts_per_count: Option<f64>,
    volts_offset: Option<f64>,
    status_bits: Option<u8>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawChannel {
    register: u16,
    #[serde(rename = "type")]
    ty: Option<String>,
    word_order: Option<String>,
    volts_per_count: Option<f64>,
    volts_offset: Option<f64>,
    status_bits: Option<u8>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPsd {
    name: Option<String>,
    // conditioned
    x: Option<RawChannel>,
    y: Option<RawChannel>,
    sum: Option<RawChannel>,
    gain_x_mm_per_v: Option<f64>,
    gain_y_mm_per_v: Option<f64>,
    offset_x_mm: Option<f64>,
    offset_y_mm: Option<f64>,
    // electrodes
    layout: Option<String>,
    length_x_mm: Option<f64>,
    length_y_mm: Option<f64>,
    x1: Option<RawChannel>,
    x2: Option<RawChannel>,
    y1: Option<RawChannel>,
    y2: Option<RawChannel>,
}

// ---------- validated stage ----------

/// One analog channel: where its value sits in the block and how counts become volts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Channel {
    /// Offset of its first register from the block start.
    pub register: u16,
    pub ty: ValueType,
    pub order: WordOrder,
    pub volts_per_count: f64,
    pub volts_offset: f64,
    /// Low bits of a 16-bit integer cleared before scaling (diagnostic bits).
    pub status_bits: u8,
}

impl Channel {
    fn status_mask(&self) -> u16 {
        if self.status_bits == 0 {
            0
        } else {
            ((1u32 << self.status_bits) - 1) as u16
        }
    }

    /// The channel's volts from the block's registers.
    pub fn volts(&self, block: &[u16]) -> Result<f64, CodecError> {
        let at = (self.register as usize).min(block.len());
        let regs = &block[at..];
        let counts = if self.status_bits > 0 && self.ty.words() == 1 && !regs.is_empty() {
            let bits = codec::regs_to_u16([regs[0]], self.order) & !self.status_mask();
            match self.ty {
                ValueType::I16 => bits as i16 as f64,
                _ => bits as f64,
            }
        } else {
            codec::decode(self.ty, self.order, regs)?
        };
        Ok(counts * self.volts_per_count + self.volts_offset)
    }

    /// Write `volts` into the block as the module would digitise it: rounded to a count,
    /// saturated at the type's range, status bits clear.
    pub fn put_volts(&self, volts: f64, block: &mut [u16]) -> Result<(), CodecError> {
        let (lo, hi) = self.ty.range();
        let mut counts = ((volts - self.volts_offset) / self.volts_per_count).clamp(lo, hi);
        if self.ty.is_integer() {
            counts = counts.round().clamp(lo, hi);
            if self.status_bits > 0 {
                counts = ((counts as i64) & !(self.status_mask() as i64)) as f64;
            }
        }
        let at = (self.register as usize).min(block.len());
        codec::encode(self.ty, self.order, counts, &mut block[at..])
    }
}

/// A PSD read through a signal processor (X, Y, SUM voltages).
#[derive(Clone, Debug, PartialEq)]
pub struct Conditioned {
    pub name: String,
    pub x: Channel,
    pub y: Channel,
    pub sum: Channel,
    pub gain_x_mm_per_v: f64,
    pub gain_y_mm_per_v: f64,
    pub offset_x_mm: f64,
    pub offset_y_mm: f64,
}

/// Two-dimensional PSD structure (Hamamatsu's terms).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lateral {
    /// Resistive layers on both sides: X electrodes on one, Y on the other.
    DuoLateral,
    /// Four electrodes along the edges of one resistive layer.
    TetraLateral,
}

/// A PSD read as four electrode signals.
#[derive(Clone, Debug, PartialEq)]
pub struct Electrodes {
    pub name: String,
    pub layout: Lateral,
    /// Active lengths Lx, Ly (mm), electrode to electrode.
    pub length_x_mm: f64,
    pub length_y_mm: f64,
    pub x1: Channel,
    pub x2: Channel,
    pub y1: Channel,
    pub y2: Channel,
}

/// How one PSD is read.
#[derive(Clone, Debug, PartialEq)]
pub enum PsdMap {
    Conditioned(Conditioned),
    Electrodes(Electrodes),
}

impl PsdMap {
    pub fn name(&self) -> &str {
        match self {
            PsdMap::Conditioned(c) => &c.name,
            PsdMap::Electrodes(e) => &e.name,
        }
    }
}

/// A validated I/O-module map.
#[derive(Clone, Debug, PartialEq)]
pub struct IoMap {
    /// The file it came from (for messages).
    pub file: String,
    pub name: String,
    pub kind: RegisterKind,
    pub unit_id: u8,
    /// The one block read per frame.
    pub block: ReadRange,
    /// Below this SUM (V) a PSD has no spot.
    pub sum_threshold_v: f64,
    pub psds: [PsdMap; 3],
}

const CONDITIONED_KEYS: [&str; 7] = [
    "x",
    "y",
    "sum",
    "gain_x_mm_per_v",
    "gain_y_mm_per_v",
    "offset_x_mm",
    "offset_y_mm",
];
const ELECTRODE_KEYS: [&str; 7] = [
    "layout",
    "length_x_mm",
    "length_y_mm",
    "x1",
    "x2",
    "y1",
    "y2",
];

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

    /// `v` within `r`, or an error naming `key` with the range, and `fix`.
    fn range(&self, key: &str, v: f64, r: Range, fix: &str) -> Result<f64, MapError> {
        r.check(v).map_err(|p| self.err(key, p, fix))
    }
}

// What a module and a PSD can be: signals within ±100 V, a count from 1 nV to 10 V, gains
// from 1 µm to 1 m per volt (negative for an inverted axis), offsets and active lengths
// within a PSD's size.
const SUM_THRESHOLD: Range = Range::new(0.0, 100.0, "V");
const VOLTS_PER_COUNT: Range = Range::new(1e-9, 10.0, "V").either_sign();
const VOLTS_OFFSET: Range = Range::symmetric(100.0, "V");
const GAIN: Range = Range::new(0.001, 1000.0, "mm/V").either_sign();
const OFFSET: Range = Range::symmetric(100.0, "mm");
const LENGTH: Range = Range::new(0.1, 100.0, "mm");

impl IoMap {
    /// Load and validate a map file.
    pub fn load(path: &Path) -> Result<IoMap, MapError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| MapError::Read {
            file: file.clone(),
            source,
        })?;
        IoMap::parse(&text, &file)
    }

    /// The built-in generic map (axiscomp's own layout, the twin's default).
    pub fn generic() -> Result<IoMap, MapError> {
        IoMap::parse(GENERIC_TOML, GENERIC_PATH)
    }

    /// Parse and validate map text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<IoMap, MapError> {
        let raw: RawMap = toml::from_str(text).map_err(|e| MapError::Syntax {
            file: file.to_string(),
            message: e.to_string().trim().replace('\n', " "),
        })?;
        validate(raw, &Ctx { file })
    }

    /// Registers of the block.
    pub fn block_len(&self) -> usize {
        self.block.count() as usize
    }
}

fn validate(raw: RawMap, cx: &Ctx) -> Result<IoMap, MapError> {
    if raw.name.trim().is_empty() {
        return Err(cx.err("name", "empty", "name the module (shown in the console)"));
    }
    let block = ReadRange::new(raw.block_start, raw.block_length).map_err(|e| {
        cx.err(
            "block_length",
            e.to_string(),
            "one block read carries 1 to 125 registers inside 0 to 65535",
        )
    })?;
    let threshold = cx.range(
        "sum_threshold_v",
        raw.sum_threshold_v,
        SUM_THRESHOLD,
        "give the SUM (V) below which a PSD has no spot, e.g. 0.5",
    )?;
    let electrodes = match raw.mode.as_str() {
        "conditioned" => false,
        "electrodes" => true,
        other => {
            return Err(cx.err(
                "mode",
                format!("unknown mode {other:?}"),
                "use \"conditioned\" (X, Y, SUM voltages) or \"electrodes\" (four electrode signals)",
            ));
        }
    };
    if raw.psd.len() != 3 {
        return Err(cx.err(
            "psd",
            format!("{} [[psd]] tables", raw.psd.len()),
            "give exactly three [[psd]] tables, PSD1 to PSD3 in order",
        ));
    }
    let mut used: BTreeMap<u16, String> = BTreeMap::new();
    let mut psds = Vec::with_capacity(3);
    for (i, p) in raw.psd.into_iter().enumerate() {
        psds.push(psd(p, i, electrodes, &raw.defaults, block, &mut used, cx)?);
    }
    let psds: [PsdMap; 3] = psds
        .try_into()
        .map_err(|_| cx.err("psd", "not three PSDs", "give exactly three [[psd]] tables"))?;
    Ok(IoMap {
        file: cx.file.to_string(),
        name: raw.name,
        kind: raw.register,
        unit_id: raw.unit_id,
        block,
        sum_threshold_v: threshold,
        psds,
    })
}

fn psd(
    p: RawPsd,
    i: usize,
    electrodes: bool,
    d: &RawDefaults,
    block: ReadRange,
    used: &mut BTreeMap<u16, String>,
    cx: &Ctx,
) -> Result<PsdMap, MapError> {
    let at = format!("psd[{i}]");
    let name = p.name.clone().unwrap_or_else(|| format!("PSD{}", i + 1));
    let present = |k: &str| -> bool {
        match k {
            "x" => p.x.is_some(),
            "y" => p.y.is_some(),
            "sum" => p.sum.is_some(),
            "gain_x_mm_per_v" => p.gain_x_mm_per_v.is_some(),
            "gain_y_mm_per_v" => p.gain_y_mm_per_v.is_some(),
            "offset_x_mm" => p.offset_x_mm.is_some(),
            "offset_y_mm" => p.offset_y_mm.is_some(),
            "layout" => p.layout.is_some(),
            "length_x_mm" => p.length_x_mm.is_some(),
            "length_y_mm" => p.length_y_mm.is_some(),
            "x1" => p.x1.is_some(),
            "x2" => p.x2.is_some(),
            "y1" => p.y1.is_some(),
            "y2" => p.y2.is_some(),
            _ => false,
        }
    };
    let (foreign, mode, other) = if electrodes {
        (&CONDITIONED_KEYS, "electrodes", "conditioned")
    } else {
        (&ELECTRODE_KEYS, "conditioned", "electrodes")
    };
    if let Some(k) = foreign.iter().find(|k| present(k)) {
        return Err(cx.err(
            format!("{at}.{k}"),
            format!("a key of mode \"{other}\" in a map with mode = \"{mode}\""),
            &format!("remove it, or set mode = \"{other}\" and give that mode's keys"),
        ));
    }
    let mut need = |k: &str, v: Option<RawChannel>| -> Result<Channel, MapError> {
        let c = v.ok_or_else(|| {
            cx.err(
                format!("{at}.{k}"),
                "missing",
                &format!("give {k} = {{ register = <offset in the block> }}"),
            )
        })?;
        channel(c, &format!("{at}.{k}"), d, block, used, cx)
    };
    let number = |k: &str, v: Option<f64>, default: Option<f64>, r: Range| {
        let v = v.or(default).ok_or_else(|| {
            cx.err(
                format!("{at}.{k}"),
                "missing",
                "give it (see plc-maps/io/generic.toml)",
            )
        })?;
        cx.range(
            &format!("{at}.{k}"),
            v,
            r,
            "give the PSD's value (see plc-maps/io/generic.toml)",
        )
    };
    if electrodes {
        let layout = match p.layout.as_deref() {
            Some("duo-lateral") => Lateral::DuoLateral,
            Some("tetra-lateral") => Lateral::TetraLateral,
            other => {
                return Err(cx.err(
                    format!("{at}.layout"),
                    match other {
                        Some(s) => format!("unknown PSD layout {s:?}"),
                        None => "missing".to_string(),
                    },
                    "use \"duo-lateral\" or \"tetra-lateral\" (pin-cushion PSDs are not supported)",
                ));
            }
        };
        let lx = number("length_x_mm", p.length_x_mm, None, LENGTH)?;
        let ly = number("length_y_mm", p.length_y_mm, None, LENGTH)?;
        Ok(PsdMap::Electrodes(Electrodes {
            name,
            layout,
            length_x_mm: lx,
            length_y_mm: ly,
            x1: need("x1", p.x1)?,
            x2: need("x2", p.x2)?,
            y1: need("y1", p.y1)?,
            y2: need("y2", p.y2)?,
        }))
    } else {
        Ok(PsdMap::Conditioned(Conditioned {
            name,
            gain_x_mm_per_v: number("gain_x_mm_per_v", p.gain_x_mm_per_v, None, GAIN)?,
            gain_y_mm_per_v: number("gain_y_mm_per_v", p.gain_y_mm_per_v, None, GAIN)?,
            offset_x_mm: number("offset_x_mm", p.offset_x_mm, Some(0.0), OFFSET)?,
            offset_y_mm: number("offset_y_mm", p.offset_y_mm, Some(0.0), OFFSET)?,
            x: need("x", p.x)?,
            y: need("y", p.y)?,
            sum: need("sum", p.sum)?,
        }))
    }
}

fn channel(
    c: RawChannel,
    key: &str,
    d: &RawDefaults,
    block: ReadRange,
    used: &mut BTreeMap<u16, String>,
    cx: &Ctx,
) -> Result<Channel, MapError> {
    let ty: ValueType = match c.ty.as_deref().or(d.ty.as_deref()) {
        Some(s) => s
            .parse()
            .map_err(|e: String| cx.err(format!("{key}.type"), e, "fix the type"))?,
        None => {
            return Err(cx.err(
                format!("{key}.type"),
                "missing",
                "give type here or in [defaults] (u16, i16, u32, i32, f32)",
            ));
        }
    };
    let order: WordOrder = match c.word_order.as_deref().or(d.word_order.as_deref()) {
        Some(s) => s
            .parse()
            .map_err(|e: String| cx.err(format!("{key}.word_order"), e, "fix the word order"))?,
        None => WordOrder::Abcd,
    };
    let vpc = c.volts_per_count.or(d.volts_per_count).ok_or_else(|| {
        cx.err(
            format!("{key}.volts_per_count"),
            "missing",
            "give volts_per_count here or in [defaults] (full-scale volts / full-scale counts)",
        )
    })?;
    let vpc = cx.range(
        &format!("{key}.volts_per_count"),
        vpc,
        VOLTS_PER_COUNT,
        "give the module's full-scale volts / full-scale counts",
    )?;
    let voff = cx.range(
        &format!("{key}.volts_offset"),
        c.volts_offset.or(d.volts_offset).unwrap_or(0.0),
        VOLTS_OFFSET,
        "give the volts at 0 counts (usually 0)",
    )?;
    let status_bits = c.status_bits.or(d.status_bits).unwrap_or(0);
    if status_bits > 0 && (ty.words() != 1 || status_bits > 15) {
        return Err(cx.err(
            format!("{key}.status_bits"),
            format!("{status_bits} status bits on a {ty} channel"),
            "status bits apply to 16-bit integer channels only, at most 15",
        ));
    }
    let words = ty.words();
    if c.register as u32 + words as u32 > block.count() as u32 {
        return Err(cx.err(
            format!("{key}.register"),
            format!(
                "offset {} ({ty}, {words} register(s)) runs past the block of {} registers",
                c.register,
                block.count()
            ),
            "registers are offsets from block_start: use a smaller offset or raise block_length",
        ));
    }
    for r in c.register..c.register + words {
        if let Some(other) = used.insert(r, key.to_string()) {
            return Err(cx.err(
                format!("{key}.register"),
                format!("block register {r} is already used by {other}"),
                "give every channel its own registers",
            ));
        }
    }
    Ok(Channel {
        register: c.register,
        ty,
        order,
        volts_per_count: vpc,
        volts_offset: voff,
        status_bits,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn maps_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("plc-maps/io")
    }

    fn fixtures() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/io-maps")
    }

    #[test]
    fn shipped_maps_are_valid() {
        let mut n = 0;
        for e in std::fs::read_dir(maps_dir()).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                let m = IoMap::load(&p).unwrap_or_else(|e| panic!("{e}"));
                assert!(m.block.count() >= 9, "{}", p.display());
                n += 1;
            }
        }
        assert!(n >= 3, "generic plus two product maps");
    }

    #[test]
    fn generic_map_layout() {
        let m = IoMap::generic().unwrap();
        assert_eq!(m.kind, RegisterKind::Input);
        assert_eq!(m.unit_id, 1);
        assert_eq!((m.block.start(), m.block.count()), (0, 9));
        let PsdMap::Conditioned(c) = &m.psds[1] else {
            panic!("conditioned")
        };
        assert_eq!((c.x.register, c.y.register, c.sum.register), (3, 4, 5));
        assert_eq!(c.x.ty, ValueType::I16);
        assert!((c.x.volts_per_count - 10.0 / 32767.0).abs() < 1e-15);
    }

    #[test]
    fn channel_volts_with_status_bits() {
        let c = Channel {
            register: 1,
            ty: ValueType::I16,
            order: WordOrder::Abcd,
            volts_per_count: 10.0 / 32768.0,
            volts_offset: 0.0,
            status_bits: 3,
        };
        // WAGO 750-456: +10 V reads 0x7FF8; overflow sets the low bit (0x7FF9).
        assert_eq!(c.volts(&[0, 0x7FF9]).unwrap(), 32760.0 * 10.0 / 32768.0);
        assert_eq!(c.volts(&[0, 0x8000]).unwrap(), -10.0);
        let mut b = [0u16; 2];
        c.put_volts(5.0, &mut b).unwrap();
        assert_eq!(b[1], 0x4000);
        c.put_volts(1.0, &mut b).unwrap(); // 3276.8 → 3277 → 3272 with 3 bits cleared
        assert_eq!(b[1], 3272);
        c.put_volts(-20.0, &mut b).unwrap(); // saturates like the ADC
        assert_eq!(b[1], 0x8000);
    }

    /// Every invalid fixture fails naming its file and the key it was written to test.
    #[test]
    fn invalid_fixtures_name_file_and_key() {
        let cases: [(&str, &str); 16] = [
            ("block-too-long.toml", "block_length"),
            ("block-zero.toml", "block_length"),
            ("bad-mode.toml", "mode"),
            ("two-psds.toml", "psd"),
            ("channel-past-block.toml", "psd[2].sum.register"),
            ("overlap.toml", "psd[1].x.register"),
            ("bad-type.toml", "psd[0].y.type"),
            ("bad-word-order.toml", "psd[0].x.word_order"),
            ("zero-scale.toml", "psd[0].x.volts_per_count"),
            ("missing-gain.toml", "psd[1].gain_y_mm_per_v"),
            ("missing-channel.toml", "psd[0].sum"),
            ("electrode-key-in-conditioned.toml", "psd[0].x1"),
            ("bad-layout.toml", "psd[1].layout"),
            ("negative-threshold.toml", "sum_threshold_v"),
            ("status-bits-on-f32.toml", "psd[0].x.status_bits"),
            ("zero-length.toml", "psd[2].length_y_mm"),
        ];
        for (file, key) in cases {
            let path = fixtures().join(file);
            let err = IoMap::load(&path).expect_err(file);
            let msg = err.to_string();
            assert_eq!(err.key(), Some(key), "{file}: {msg}");
            assert!(msg.contains(file), "{msg}");
            assert!(msg.contains(&format!("`{key}`")), "{msg}");
        }
    }

    #[test]
    fn syntax_errors_name_file_and_field() {
        for (file, word) in [
            ("unknown-key.toml", "sum_treshold_v"),
            ("unknown-channel-key.toml", "scale"),
            ("bad-register-kind.toml", "register"),
            ("unit-id-too-big.toml", "unit_id"),
        ] {
            let err = IoMap::load(&fixtures().join(file)).expect_err(file);
            assert!(matches!(err, MapError::Syntax { .. }), "{file}: {err}");
            let msg = err.to_string();
            assert!(msg.contains(file) && msg.contains(word), "{file}: {msg}");
        }
        let err = IoMap::load(&fixtures().join("no-such-file.toml")).unwrap_err();
        assert!(matches!(err, MapError::Read { .. }));
        assert!(err.to_string().contains("no-such-file.toml"));
    }
}
