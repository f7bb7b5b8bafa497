//! Register codecs and validated addresses (sans-I/O, pure functions).
//!
//! A Modbus register is a 16-bit word sent high byte first. Values wider than one register,
//! and devices that store bytes in an unexpected order, are described by a [`WordOrder`]
//! named after where the value's big-endian bytes `A B C D` (A most significant) land:
//!
//! | order | register 0 | register 1 | seen on |
//! |---|---|---|---|
//! | `ABCD` | `A B` | `C D` | the Modbus convention (big-endian words) |
//! | `CDAB` | `C D` | `A B` | low word first ("word swap"): many PLCs and I/O modules |
//! | `BADC` | `B A` | `D C` | bytes swapped in each word, words big-endian |
//! | `DCBA` | `D C` | `B A` | fully little-endian |
//!
//! For 16-bit values only the byte order matters: `ABCD`/`CDAB` leave the register as it is,
//! `BADC`/`DCBA` swap its two bytes (a coupler set to "Intel"/"Motorola" format the wrong way).
//!
//! Addresses are 0-based PDU addresses (register 40001 in a manual's 1-based "4x" notation is
//! address 0 of the holding registers). [`ReadRange`] and [`WriteRange`] enforce the
//! protocol's quantity limits (Modbus Application Protocol v1.1b3, §6.3/§6.4: 1..=125 registers
//! per read; §6.12: 1..=123 per write) and that the range stays inside the 65 536-register
//! space, so an invalid request cannot be built.

use std::fmt;
use std::str::FromStr;
use thiserror::Error;

/// Most registers one read (function 3 or 4) may return.
pub const MAX_READ: u16 = 125;
/// Most registers one write-multiple (function 16) may carry.
pub const MAX_WRITE: u16 = 123;

/// Where a value's bytes sit in its registers (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum WordOrder {
    /// Big-endian words, big-endian bytes (the Modbus convention).
    #[default]
    Abcd,
    /// Little-endian word order (word swap), big-endian bytes.
    Cdab,
    /// Big-endian word order, bytes swapped within each word.
    Badc,
    /// Fully little-endian.
    Dcba,
}

impl WordOrder {
    /// All orders, for tests and error messages.
    pub const ALL: [WordOrder; 4] = [
        WordOrder::Abcd,
        WordOrder::Cdab,
        WordOrder::Badc,
        WordOrder::Dcba,
    ];

    /// The order's name as written in maps.
    pub fn name(self) -> &'static str {
        match self {
            WordOrder::Abcd => "ABCD",
            WordOrder::Cdab => "CDAB",
            WordOrder::Badc => "BADC",
            WordOrder::Dcba => "DCBA",
        }
    }

    fn swaps_words(self) -> bool {
        matches!(self, WordOrder::Cdab | WordOrder::Dcba)
    }

    fn swaps_bytes(self) -> bool {
        matches!(self, WordOrder::Badc | WordOrder::Dcba)
    }
}

impl fmt::Display for WordOrder {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for WordOrder {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        WordOrder::ALL
            .into_iter()
            .find(|o| o.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| format!("unknown word order {s:?}: use ABCD, CDAB, BADC or DCBA"))
    }
}

/// A register value type.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ValueType {
    U16,
    I16,
    U32,
    I32,
    F32,
}

impl ValueType {
    /// All types, for tests and error messages.
    pub const ALL: [ValueType; 5] = [
        ValueType::U16,
        ValueType::I16,
        ValueType::U32,
        ValueType::I32,
        ValueType::F32,
    ];

    /// Registers the type occupies.
    pub const fn words(self) -> u16 {
        match self {
            ValueType::U16 | ValueType::I16 => 1,
            ValueType::U32 | ValueType::I32 | ValueType::F32 => 2,
        }
    }

    /// The type's name as written in maps.
    pub fn name(self) -> &'static str {
        match self {
            ValueType::U16 => "u16",
            ValueType::I16 => "i16",
            ValueType::U32 => "u32",
            ValueType::I32 => "i32",
            ValueType::F32 => "f32",
        }
    }

    /// Whether the type is an integer (so counts are whole numbers).
    pub const fn is_integer(self) -> bool {
        !matches!(self, ValueType::F32)
    }

    /// The smallest and largest value the type holds.
    pub fn range(self) -> (f64, f64) {
        match self {
            ValueType::U16 => (0.0, u16::MAX as f64),
            ValueType::I16 => (i16::MIN as f64, i16::MAX as f64),
            ValueType::U32 => (0.0, u32::MAX as f64),
            ValueType::I32 => (i32::MIN as f64, i32::MAX as f64),
            ValueType::F32 => (f32::MIN as f64, f32::MAX as f64),
        }
    }
}

impl fmt::Display for ValueType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for ValueType {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        ValueType::ALL
            .into_iter()
            .find(|t| t.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| format!("unknown type {s:?}: use u16, i16, u32, i32 or f32"))
    }
}

/// Why registers could not be encoded or decoded.
#[derive(Clone, Copy, Debug, Error, PartialEq)]
pub enum CodecError {
    #[error("{ty} needs {need} register(s), got {got}")]
    Short {
        ty: ValueType,
        need: u16,
        got: usize,
    },
    #[error("{value} does not fit in {ty}")]
    OutOfRange { ty: ValueType, value: f64 },
    #[error("{ty} cannot hold a non-finite value")]
    NotFinite { ty: ValueType },
}

/// One register from two bytes, in `order`.
fn word(hi: u8, lo: u8, order: WordOrder) -> u16 {
    if order.swaps_bytes() {
        u16::from_le_bytes([hi, lo])
    } else {
        u16::from_be_bytes([hi, lo])
    }
}

fn bytes(w: u16, order: WordOrder) -> [u8; 2] {
    if order.swaps_bytes() {
        w.to_le_bytes()
    } else {
        w.to_be_bytes()
    }
}

/// A 16-bit value's register.
pub fn u16_to_regs(v: u16, order: WordOrder) -> [u16; 1] {
    let [a, b] = v.to_be_bytes();
    [word(a, b, order)]
}

/// A 16-bit value from its register.
pub fn regs_to_u16(r: [u16; 1], order: WordOrder) -> u16 {
    u16::from_be_bytes(bytes(r[0], order))
}

/// A signed 16-bit value's register (two's complement).
pub fn i16_to_regs(v: i16, order: WordOrder) -> [u16; 1] {
    u16_to_regs(v as u16, order)
}

/// A signed 16-bit value from its register.
pub fn regs_to_i16(r: [u16; 1], order: WordOrder) -> i16 {
    regs_to_u16(r, order) as i16
}

/// A 32-bit value's two registers.
pub fn u32_to_regs(v: u32, order: WordOrder) -> [u16; 2] {
    let [a, b, c, d] = v.to_be_bytes();
    let hi = word(a, b, order);
    let lo = word(c, d, order);
    if order.swaps_words() {
        [lo, hi]
    } else {
        [hi, lo]
    }
}

/// A 32-bit value from its two registers.
pub fn regs_to_u32(r: [u16; 2], order: WordOrder) -> u32 {
    let (hi, lo) = if order.swaps_words() {
        (r[1], r[0])
    } else {
        (r[0], r[1])
    };
    let [a, b] = bytes(hi, order);
    let [c, d] = bytes(lo, order);
    u32::from_be_bytes([a, b, c, d])
}

/// A signed 32-bit value's registers.
pub fn i32_to_regs(v: i32, order: WordOrder) -> [u16; 2] {
    u32_to_regs(v as u32, order)
}

/// A signed 32-bit value from its registers.
pub fn regs_to_i32(r: [u16; 2], order: WordOrder) -> i32 {
    regs_to_u32(r, order) as i32
}

/// An IEEE 754 single's registers.
pub fn f32_to_regs(v: f32, order: WordOrder) -> [u16; 2] {
    u32_to_regs(v.to_bits(), order)
}

/// An IEEE 754 single from its registers.
pub fn regs_to_f32(r: [u16; 2], order: WordOrder) -> f32 {
    f32::from_bits(regs_to_u32(r, order))
}

/// The value of type `ty` at the start of `regs`, widened to `f64` (exact for every type).
pub fn decode(ty: ValueType, order: WordOrder, regs: &[u16]) -> Result<f64, CodecError> {
    let need = ty.words();
    if regs.len() < need as usize {
        return Err(CodecError::Short {
            ty,
            need,
            got: regs.len(),
        });
    }
    let one = [regs[0]];
    Ok(match ty {
        ValueType::U16 => regs_to_u16(one, order) as f64,
        ValueType::I16 => regs_to_i16(one, order) as f64,
        ValueType::U32 => regs_to_u32([regs[0], regs[1]], order) as f64,
        ValueType::I32 => regs_to_i32([regs[0], regs[1]], order) as f64,
        ValueType::F32 => regs_to_f32([regs[0], regs[1]], order) as f64,
    })
}

/// Encode `value` as `ty` into the start of `out`: integers are rounded to the nearest count
/// and must fit the type; `f32` must be finite and in range.
pub fn encode(
    ty: ValueType,
    order: WordOrder,
    value: f64,
    out: &mut [u16],
) -> Result<(), CodecError> {
    let need = ty.words();
    if out.len() < need as usize {
        return Err(CodecError::Short {
            ty,
            need,
            got: out.len(),
        });
    }
    if !value.is_finite() {
        return Err(CodecError::NotFinite { ty });
    }
    let v = if ty.is_integer() {
        value.round()
    } else {
        value
    };
    let (lo, hi) = ty.range();
    if v < lo || v > hi {
        return Err(CodecError::OutOfRange { ty, value });
    }
    match ty {
        ValueType::U16 => out[..1].copy_from_slice(&u16_to_regs(v as u16, order)),
        ValueType::I16 => out[..1].copy_from_slice(&i16_to_regs(v as i16, order)),
        ValueType::U32 => out[..2].copy_from_slice(&u32_to_regs(v as u32, order)),
        ValueType::I32 => out[..2].copy_from_slice(&i32_to_regs(v as i32, order)),
        ValueType::F32 => out[..2].copy_from_slice(&f32_to_regs(v as f32, order)),
    }
    Ok(())
}

/// Why an address range is not a valid request.
#[derive(Clone, Copy, Debug, Error, PartialEq, Eq)]
pub enum AddressError {
    #[error("quantity {count} is outside 1 to {max}")]
    Quantity { count: u16, max: u16 },
    #[error("registers {start}..{start}+{count} run past the last address 65535")]
    PastEnd { start: u16, count: u16 },
}

fn check(start: u16, count: u16, max: u16) -> Result<(), AddressError> {
    if count == 0 || count > max {
        return Err(AddressError::Quantity { count, max });
    }
    if start as u32 + count as u32 > 0x1_0000 {
        return Err(AddressError::PastEnd { start, count });
    }
    Ok(())
}

/// A readable register range: 0-based start, 1..=125 registers, inside the address space.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ReadRange {
    start: u16,
    count: u16,
}

impl ReadRange {
    pub fn new(start: u16, count: u16) -> Result<Self, AddressError> {
        check(start, count, MAX_READ)?;
        Ok(ReadRange { start, count })
    }
    /// First register (0-based).
    pub fn start(&self) -> u16 {
        self.start
    }
    /// Number of registers.
    pub fn count(&self) -> u16 {
        self.count
    }
    /// One past the last register (up to 65 536).
    pub fn end(&self) -> u32 {
        self.start as u32 + self.count as u32
    }
    /// Whether `other` lies inside this range.
    pub fn contains(&self, other: &ReadRange) -> bool {
        other.start >= self.start && other.end() <= self.end()
    }
}

impl fmt::Display for ReadRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}..{} ({} registers)",
            self.start,
            self.end(),
            self.count
        )
    }
}

/// A writable register range: 0-based start, 1..=123 registers, inside the address space.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct WriteRange {
    start: u16,
    count: u16,
}

impl WriteRange {
    pub fn new(start: u16, count: u16) -> Result<Self, AddressError> {
        check(start, count, MAX_WRITE)?;
        Ok(WriteRange { start, count })
    }
    /// The range that `values` would occupy from `start`.
    pub fn for_values(start: u16, values: &[u16]) -> Result<Self, AddressError> {
        let count = u16::try_from(values.len()).unwrap_or(u16::MAX);
        Self::new(start, count)
    }
    pub fn start(&self) -> u16 {
        self.start
    }
    pub fn count(&self) -> u16 {
        self.count
    }
    pub fn end(&self) -> u32 {
        self.start as u32 + self.count as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use WordOrder::*;

    #[test]
    fn f32_literal_registers_in_every_order() {
        // 1.5 = 0x3FC0_0000: bytes A=3F B=C0 C=00 D=00.
        assert_eq!(f32_to_regs(1.5, Abcd), [0x3FC0, 0x0000]);
        assert_eq!(f32_to_regs(1.5, Cdab), [0x0000, 0x3FC0]);
        assert_eq!(f32_to_regs(1.5, Badc), [0xC03F, 0x0000]);
        assert_eq!(f32_to_regs(1.5, Dcba), [0x0000, 0xC03F]);
        // -2.5 = 0xC020_0000; 123.456 = 0x42F6_E979.
        assert_eq!(f32_to_regs(-2.5, Abcd), [0xC020, 0x0000]);
        assert_eq!(f32_to_regs(123.456, Abcd), [0x42F6, 0xE979]);
        assert_eq!(f32_to_regs(123.456, Cdab), [0xE979, 0x42F6]);
        assert_eq!(f32_to_regs(123.456, Badc), [0xF642, 0x79E9]);
        assert_eq!(f32_to_regs(123.456, Dcba), [0x79E9, 0xF642]);
        assert_eq!(regs_to_f32([0x79E9, 0xF642], Dcba), 123.456);
        assert_eq!(regs_to_f32([0xE979, 0x42F6], Cdab), 123.456);
    }

    #[test]
    fn u32_and_i32_literal_registers() {
        let v = 0x1234_5678u32;
        assert_eq!(u32_to_regs(v, Abcd), [0x1234, 0x5678]);
        assert_eq!(u32_to_regs(v, Cdab), [0x5678, 0x1234]);
        assert_eq!(u32_to_regs(v, Badc), [0x3412, 0x7856]);
        assert_eq!(u32_to_regs(v, Dcba), [0x7856, 0x3412]);
        for o in WordOrder::ALL {
            assert_eq!(regs_to_u32(u32_to_regs(v, o), o), v, "{o}");
        }
        // -2 = 0xFFFF_FFFE; -100000 = 0xFFFE_7960.
        assert_eq!(i32_to_regs(-2, Abcd), [0xFFFF, 0xFFFE]);
        assert_eq!(i32_to_regs(-100_000, Abcd), [0xFFFE, 0x7960]);
        assert_eq!(i32_to_regs(-100_000, Cdab), [0x7960, 0xFFFE]);
        assert_eq!(regs_to_i32([0x6079, 0xFEFF], Dcba), -100_000);
        assert_eq!(regs_to_i32([0xFEFF, 0x6079], Badc), -100_000);
    }

    #[test]
    fn sixteen_bit_values_only_care_about_byte_order() {
        assert_eq!(u16_to_regs(0x1234, Abcd), [0x1234]);
        assert_eq!(u16_to_regs(0x1234, Cdab), [0x1234]);
        assert_eq!(u16_to_regs(0x1234, Badc), [0x3412]);
        assert_eq!(u16_to_regs(0x1234, Dcba), [0x3412]);
        // -32768 = 0x8000, -1 = 0xFFFF, 3277 = 0x0CCD.
        assert_eq!(i16_to_regs(-32768, Abcd), [0x8000]);
        assert_eq!(regs_to_i16([0xFFFF], Abcd), -1);
        assert_eq!(regs_to_i16([0xCD0C], Badc), 3277);
        assert_eq!(regs_to_u16([0x0080], Dcba), 0x8000);
    }

    #[test]
    fn generic_decode_and_encode_agree_with_the_typed_codecs() {
        let cases: [(ValueType, f64); 8] = [
            (ValueType::U16, 65535.0),
            (ValueType::I16, -1234.0),
            (ValueType::U32, 4_000_000_000.0),
            (ValueType::I32, -2_000_000_000.0),
            (ValueType::F32, 1.5),
            (ValueType::F32, -0.15625),
            (ValueType::I16, 0.0),
            (ValueType::U32, 1.0),
        ];
        for (ty, v) in cases {
            for o in WordOrder::ALL {
                let mut regs = [0u16; 2];
                encode(ty, o, v, &mut regs).unwrap();
                assert_eq!(decode(ty, o, &regs).unwrap(), v, "{ty} {o}");
            }
        }
        let mut r = [0u16; 2];
        encode(ValueType::I32, Cdab, -100_000.0, &mut r).unwrap();
        assert_eq!(r, [0x7960, 0xFFFE]);
        // Integers round to the nearest count.
        encode(ValueType::I16, Abcd, 3276.7, &mut r).unwrap();
        assert_eq!(r[0], 3277);
        encode(ValueType::I16, Abcd, -0.4, &mut r).unwrap();
        assert_eq!(r[0], 0);
    }

    #[test]
    fn codec_errors() {
        let mut one = [0u16; 1];
        assert_eq!(
            encode(ValueType::F32, Abcd, 1.0, &mut one),
            Err(CodecError::Short {
                ty: ValueType::F32,
                need: 2,
                got: 1
            })
        );
        assert!(matches!(
            encode(ValueType::I16, Abcd, 40_000.0, &mut one),
            Err(CodecError::OutOfRange { .. })
        ));
        assert!(matches!(
            encode(ValueType::U16, Abcd, -1.0, &mut one),
            Err(CodecError::OutOfRange { .. })
        ));
        assert_eq!(
            encode(ValueType::I16, Abcd, f64::NAN, &mut one),
            Err(CodecError::NotFinite { ty: ValueType::I16 })
        );
        assert!(matches!(
            decode(ValueType::U32, Abcd, &[1]),
            Err(CodecError::Short { .. })
        ));
    }

    #[test]
    fn names_parse_back() {
        for o in WordOrder::ALL {
            assert_eq!(o.name().parse::<WordOrder>().unwrap(), o);
        }
        assert_eq!("cdab".parse::<WordOrder>().unwrap(), Cdab);
        assert!("ABDC".parse::<WordOrder>().is_err());
        for t in ValueType::ALL {
            assert_eq!(t.name().parse::<ValueType>().unwrap(), t);
        }
        assert!("f64".parse::<ValueType>().is_err());
    }

    #[test]
    fn ranges_enforce_the_protocol_limits() {
        assert_eq!(
            ReadRange::new(0, 0),
            Err(AddressError::Quantity { count: 0, max: 125 })
        );
        assert_eq!(
            ReadRange::new(0, 126),
            Err(AddressError::Quantity {
                count: 126,
                max: 125
            })
        );
        assert!(ReadRange::new(0, 125).is_ok());
        assert!(ReadRange::new(65535, 1).is_ok());
        assert_eq!(
            ReadRange::new(65535, 2),
            Err(AddressError::PastEnd {
                start: 65535,
                count: 2
            })
        );
        let r = ReadRange::new(65411, 125).unwrap();
        assert_eq!(r.end(), 65536);
        assert!(WriteRange::new(0, 123).is_ok());
        assert_eq!(
            WriteRange::new(0, 124),
            Err(AddressError::Quantity {
                count: 124,
                max: 123
            })
        );
        assert!(WriteRange::for_values(10, &[]).is_err());
        assert_eq!(WriteRange::for_values(10, &[1, 2]).unwrap().end(), 12);
        let block = ReadRange::new(100, 10).unwrap();
        assert!(block.contains(&ReadRange::new(100, 10).unwrap()));
        assert!(block.contains(&ReadRange::new(105, 5).unwrap()));
        assert!(!block.contains(&ReadRange::new(105, 6).unwrap()));
        assert!(!block.contains(&ReadRange::new(99, 2).unwrap()));
    }
}
