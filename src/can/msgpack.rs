//! A minimal MessagePack codec for python-can's `udp_multicast` datagrams (see `pycan`).
//!
//! Scope: exactly what those datagrams use — maps, str, bin, bool, nil, integers and floats —
//! plus arrays and ext values, so that a map with extra keys of any type can still be read
//! past. The encoder picks the shortest form for every value, as python's `msgpack.packb(...,
//! use_bin_type=True)` does, so our datagrams are byte-for-byte what python-can would send.
//! The decoder borrows strings and byte strings from the input, refuses truncated input,
//! trailing bytes, invalid UTF-8, reserved type bytes and nesting deeper than [`MAX_DEPTH`]
//! with [`CanError::Malformed`], and never allocates more than the input can justify.
//!
//! Format reference: the MessagePack specification (msgpack/msgpack `spec.md`).

use super::CanError;

/// Deepest nesting of arrays and maps the decoder accepts (python-can's maps are flat).
pub const MAX_DEPTH: usize = 16;

/// A decoded (or to-be-encoded) MessagePack value.
#[derive(Clone, Debug, PartialEq)]
pub enum Value<'a> {
    /// `nil`.
    Nil,
    /// `true` / `false`.
    Bool(bool),
    /// Any integer format (the union of int64 and uint64 fits in an `i128`).
    Int(i128),
    /// float 64 (float 32 is widened on decoding).
    Float(f64),
    /// A UTF-8 string.
    Str(&'a str),
    /// A byte string.
    Bin(&'a [u8]),
    /// An array.
    Array(Vec<Value<'a>>),
    /// A map, in wire order. Keys are not checked for repeats here (that would cost a
    /// quadratic scan on forged input); a reader that cares checks its own keys.
    Map(Vec<(Value<'a>, Value<'a>)>),
    /// An extension value: type and payload.
    Ext(i8, &'a [u8]),
}

impl<'a> Value<'a> {
    /// The value under the first string key `key` of a map; `None` if this is not a map or
    /// the key is absent.
    pub fn get(&self, key: &str) -> Option<&Value<'a>> {
        match self {
            Value::Map(entries) => entries
                .iter()
                .find(|(k, _)| matches!(k, Value::Str(s) if *s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    /// A short name of the value's type, for error messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Value::Nil => "nil",
            Value::Bool(_) => "bool",
            Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Bin(_) => "bin",
            Value::Array(_) => "array",
            Value::Map(_) => "map",
            Value::Ext(..) => "ext",
        }
    }
}

/// Append the encoding of `v` to `out`.
///
/// Integers outside `-2^63 ..= 2^64 − 1`, strings/byte strings/arrays/maps longer than
/// `u32::MAX` cannot be represented; the encoder clamps nothing and instead refuses them with
/// [`CanError::Malformed`] (our own values never come near these limits).
pub fn encode(v: &Value<'_>, out: &mut Vec<u8>) -> Result<(), CanError> {
    match v {
        Value::Nil => out.push(0xc0),
        Value::Bool(false) => out.push(0xc2),
        Value::Bool(true) => out.push(0xc3),
        Value::Int(i) => encode_int(*i, out)?,
        Value::Float(f) => {
            out.push(0xcb);
            out.extend_from_slice(&f.to_bits().to_be_bytes());
        }
        Value::Str(s) => {
            let n = len32(s.len(), "str")?;
            if n < 32 {
                out.push(0xa0 | n as u8);
            } else {
                put_len(out, n, [0xd9, 0xda, 0xdb]);
            }
            out.extend_from_slice(s.as_bytes());
        }
        Value::Bin(b) => {
            put_len(out, len32(b.len(), "bin")?, [0xc4, 0xc5, 0xc6]);
            out.extend_from_slice(b);
        }
        Value::Array(items) => {
            let n = len32(items.len(), "array")?;
            if n < 16 {
                out.push(0x90 | n as u8);
            } else {
                put_len16_32(out, n, [0xdc, 0xdd]);
            }
            for item in items {
                encode(item, out)?;
            }
        }
        Value::Map(entries) => {
            let n = len32(entries.len(), "map")?;
            if n < 16 {
                out.push(0x80 | n as u8);
            } else {
                put_len16_32(out, n, [0xde, 0xdf]);
            }
            for (k, v) in entries {
                encode(k, out)?;
                encode(v, out)?;
            }
        }
        Value::Ext(ty, data) => {
            let n = len32(data.len(), "ext")?;
            let fixed = match n {
                1 => Some(0xd4),
                2 => Some(0xd5),
                4 => Some(0xd6),
                8 => Some(0xd7),
                16 => Some(0xd8),
                _ => None,
            };
            match fixed {
                Some(tag) => out.push(tag),
                None => put_len(out, n, [0xc7, 0xc8, 0xc9]),
            }
            out.push(*ty as u8);
            out.extend_from_slice(data);
        }
    }
    Ok(())
}

fn len32(n: usize, what: &str) -> Result<u32, CanError> {
    u32::try_from(n).map_err(|_| CanError::Malformed(format!("{what} of {n} items is too long")))
}

/// Length with 8-, 16- and 32-bit forms (str 8/16/32, bin 8/16/32, ext 8/16/32).
fn put_len(out: &mut Vec<u8>, n: u32, tags: [u8; 3]) {
    if let Ok(b) = u8::try_from(n) {
        out.push(tags[0]);
        out.push(b);
    } else {
        put_len16_32(out, n, [tags[1], tags[2]]);
    }
}

/// Length with 16- and 32-bit forms (array 16/32, map 16/32).
fn put_len16_32(out: &mut Vec<u8>, n: u32, tags: [u8; 2]) {
    if let Ok(h) = u16::try_from(n) {
        out.push(tags[0]);
        out.extend_from_slice(&h.to_be_bytes());
    } else {
        out.push(tags[1]);
        out.extend_from_slice(&n.to_be_bytes());
    }
}

/// Shortest form, unsigned formats for non-negative values (as python's msgpack does).
fn encode_int(i: i128, out: &mut Vec<u8>) -> Result<(), CanError> {
    if i >= 0 {
        if i < 0x80 {
            out.push(i as u8);
        } else if let Ok(v) = u8::try_from(i) {
            out.extend_from_slice(&[0xcc, v]);
        } else if let Ok(v) = u16::try_from(i) {
            out.push(0xcd);
            out.extend_from_slice(&v.to_be_bytes());
        } else if let Ok(v) = u32::try_from(i) {
            out.push(0xce);
            out.extend_from_slice(&v.to_be_bytes());
        } else if let Ok(v) = u64::try_from(i) {
            out.push(0xcf);
            out.extend_from_slice(&v.to_be_bytes());
        } else {
            return Err(CanError::Malformed(format!("integer {i} exceeds uint64")));
        }
    } else if i >= -32 {
        out.push(i as i8 as u8);
    } else if let Ok(v) = i8::try_from(i) {
        out.extend_from_slice(&[0xd0, v as u8]);
    } else if let Ok(v) = i16::try_from(i) {
        out.push(0xd1);
        out.extend_from_slice(&v.to_be_bytes());
    } else if let Ok(v) = i32::try_from(i) {
        out.push(0xd2);
        out.extend_from_slice(&v.to_be_bytes());
    } else if let Ok(v) = i64::try_from(i) {
        out.push(0xd3);
        out.extend_from_slice(&v.to_be_bytes());
    } else {
        return Err(CanError::Malformed(format!("integer {i} is below int64")));
    }
    Ok(())
}

/// Decode exactly one value that fills all of `buf`.
pub fn decode(buf: &[u8]) -> Result<Value<'_>, CanError> {
    let mut r = Reader { buf, pos: 0 };
    let v = r.value(0)?;
    if r.pos != buf.len() {
        return Err(CanError::Malformed(format!(
            "msgpack: {} trailing bytes after the value at offset {}",
            buf.len() - r.pos,
            r.pos
        )));
    }
    Ok(v)
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], CanError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        match end {
            Some(end) => {
                let s = &self.buf[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(CanError::Malformed(format!(
                "msgpack: truncated: need {n} bytes at offset {}, have {}",
                self.pos,
                self.buf.len() - self.pos
            ))),
        }
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], CanError> {
        let s = self.take(N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    fn u8(&mut self) -> Result<u8, CanError> {
        Ok(self.array::<1>()?[0])
    }
    fn u16(&mut self) -> Result<u16, CanError> {
        Ok(u16::from_be_bytes(self.array()?))
    }
    fn u32(&mut self) -> Result<u32, CanError> {
        Ok(u32::from_be_bytes(self.array()?))
    }
    fn u64(&mut self) -> Result<u64, CanError> {
        Ok(u64::from_be_bytes(self.array()?))
    }

    fn str(&mut self, n: usize) -> Result<Value<'a>, CanError> {
        let at = self.pos;
        let bytes = self.take(n)?;
        std::str::from_utf8(bytes)
            .map(Value::Str)
            .map_err(|e| CanError::Malformed(format!("msgpack: str at offset {at}: {e}")))
    }

    fn ext(&mut self, n: usize) -> Result<Value<'a>, CanError> {
        let ty = self.u8()? as i8;
        Ok(Value::Ext(ty, self.take(n)?))
    }

    /// `n` items follow, each at least one byte: refuse counts the rest cannot hold, so a
    /// forged count never drives a large allocation.
    fn check_count(&self, n: usize, per_item: usize) -> Result<(), CanError> {
        let left = self.buf.len() - self.pos;
        if n.saturating_mul(per_item) > left {
            return Err(CanError::Malformed(format!(
                "msgpack: truncated: {n} items announced at offset {}, only {left} bytes left",
                self.pos
            )));
        }
        Ok(())
    }

    fn items(&mut self, n: usize, depth: usize) -> Result<Value<'a>, CanError> {
        self.check_count(n, 1)?;
        let mut v = Vec::with_capacity(n);
        for _ in 0..n {
            v.push(self.value(depth + 1)?);
        }
        Ok(Value::Array(v))
    }

    fn entries(&mut self, n: usize, depth: usize) -> Result<Value<'a>, CanError> {
        self.check_count(n, 2)?;
        let mut v: Vec<(Value<'a>, Value<'a>)> = Vec::with_capacity(n);
        for _ in 0..n {
            let k = self.value(depth + 1)?;
            let val = self.value(depth + 1)?;
            v.push((k, val));
        }
        Ok(Value::Map(v))
    }

    fn value(&mut self, depth: usize) -> Result<Value<'a>, CanError> {
        if depth > MAX_DEPTH {
            return Err(CanError::Malformed(format!(
                "msgpack: nesting deeper than {MAX_DEPTH} at offset {}",
                self.pos
            )));
        }
        let at = self.pos;
        let b = self.u8()?;
        Ok(match b {
            0x00..=0x7f => Value::Int(b as i128),
            0x80..=0x8f => self.entries((b & 0x0f) as usize, depth)?,
            0x90..=0x9f => self.items((b & 0x0f) as usize, depth)?,
            0xa0..=0xbf => self.str((b & 0x1f) as usize)?,
            0xc0 => Value::Nil,
            0xc2 => Value::Bool(false),
            0xc3 => Value::Bool(true),
            0xc4 => {
                let n = self.u8()? as usize;
                Value::Bin(self.take(n)?)
            }
            0xc5 => {
                let n = self.u16()? as usize;
                Value::Bin(self.take(n)?)
            }
            0xc6 => {
                let n = self.u32()? as usize;
                Value::Bin(self.take(n)?)
            }
            0xc7 => {
                let n = self.u8()? as usize;
                self.ext(n)?
            }
            0xc8 => {
                let n = self.u16()? as usize;
                self.ext(n)?
            }
            0xc9 => {
                let n = self.u32()? as usize;
                self.ext(n)?
            }
            0xca => Value::Float(f32::from_bits(self.u32()?) as f64),
            0xcb => Value::Float(f64::from_bits(self.u64()?)),
            0xcc => Value::Int(self.u8()? as i128),
            0xcd => Value::Int(self.u16()? as i128),
            0xce => Value::Int(self.u32()? as i128),
            0xcf => Value::Int(self.u64()? as i128),
            0xd0 => Value::Int(self.u8()? as i8 as i128),
            0xd1 => Value::Int(self.u16()? as i16 as i128),
            0xd2 => Value::Int(self.u32()? as i32 as i128),
            0xd3 => Value::Int(self.u64()? as i64 as i128),
            0xd4 => self.ext(1)?,
            0xd5 => self.ext(2)?,
            0xd6 => self.ext(4)?,
            0xd7 => self.ext(8)?,
            0xd8 => self.ext(16)?,
            0xd9 => {
                let n = self.u8()? as usize;
                self.str(n)?
            }
            0xda => {
                let n = self.u16()? as usize;
                self.str(n)?
            }
            0xdb => {
                let n = self.u32()? as usize;
                self.str(n)?
            }
            0xdc => {
                let n = self.u16()? as usize;
                self.items(n, depth)?
            }
            0xdd => {
                let n = self.u32()? as usize;
                self.items(n, depth)?
            }
            0xde => {
                let n = self.u16()? as usize;
                self.entries(n, depth)?
            }
            0xdf => {
                let n = self.u32()? as usize;
                self.entries(n, depth)?
            }
            0xe0..=0xff => Value::Int(b as i8 as i128),
            0xc1 => {
                return Err(CanError::Malformed(format!(
                    "msgpack: reserved type byte 0xc1 at offset {at}"
                )));
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }

    fn enc(v: &Value<'_>) -> Vec<u8> {
        let mut out = Vec::new();
        encode(v, &mut out).unwrap();
        out
    }

    fn malformed(buf: &[u8]) -> String {
        match decode(buf) {
            Err(CanError::Malformed(m)) => m,
            other => panic!("expected Malformed for {buf:02x?}, got {other:?}"),
        }
    }

    /// Every literal below was produced on this machine with python's msgpack 1.2.4:
    /// `python3 -c "import msgpack; print(msgpack.packb(V, use_bin_type=True).hex())"`
    /// for the python value V written in the comment of each row.
    #[test]
    fn scalars_match_python_msgpack_both_ways() {
        let x31 = "x".repeat(31);
        let x32 = "x".repeat(32);
        let cases: Vec<(Value<'_>, String)> = vec![
            (Value::Nil, "c0".into()),                                   // None
            (Value::Bool(true), "c3".into()),                            // True
            (Value::Bool(false), "c2".into()),                           // False
            (Value::Int(0), "00".into()),                                // 0
            (Value::Int(127), "7f".into()),                              // 127
            (Value::Int(128), "cc80".into()),                            // 128
            (Value::Int(255), "ccff".into()),                            // 255
            (Value::Int(256), "cd0100".into()),                          // 256
            (Value::Int(65535), "cdffff".into()),                        // 65535
            (Value::Int(65536), "ce00010000".into()),                    // 65536
            (Value::Int(4294967295), "ceffffffff".into()),               // 2**32-1
            (Value::Int(4294967296), "cf0000000100000000".into()),       // 2**32
            (Value::Int(u64::MAX as i128), "cfffffffffffffffff".into()), // 2**64-1
            (Value::Int(-1), "ff".into()),                               // -1
            (Value::Int(-32), "e0".into()),                              // -32
            (Value::Int(-33), "d0df".into()),                            // -33
            (Value::Int(-128), "d080".into()),                           // -128
            (Value::Int(-129), "d1ff7f".into()),                         // -129
            (Value::Int(-32768), "d18000".into()),                       // -32768
            (Value::Int(-32769), "d2ffff7fff".into()),                   // -32769
            (Value::Int(-2147483648), "d280000000".into()),              // -2**31
            (Value::Int(-2147483649), "d3ffffffff7fffffff".into()),      // -2**31-1
            (Value::Int(i64::MIN as i128), "d38000000000000000".into()), // -2**63
            (Value::Float(1.5), "cb3ff8000000000000".into()),            // 1.5
            (Value::Float(0.1), "cb3fb999999999999a".into()),            // 0.1
            (Value::Float(-2.0), "cbc000000000000000".into()),           // -2.0
            (Value::Str(""), "a0".into()),                               // ""
            (Value::Str("abc"), "a3616263".into()),                      // "abc"
            (Value::Str(&x31), format!("bf{}", "78".repeat(31))),        // "x"*31
            (Value::Str(&x32), format!("d920{}", "78".repeat(32))),      // "x"*32
            (Value::Str("é"), "a2c3a9".into()),                          // "é"
            (Value::Bin(b""), "c400".into()),                            // b""
            (Value::Bin(&[1, 2, 0xff]), "c4030102ff".into()),            // b"\x01\x02\xff"
            (Value::Map(vec![]), "80".into()),                           // {}
            (Value::Array(vec![]), "90".into()),                         // []
            (
                Value::Array(vec![Value::Int(1), Value::Str("a"), Value::Nil]),
                "9301a161c0".into(), // [1, "a", None]
            ),
        ];
        for (v, h) in &cases {
            assert_eq!(enc(v), hex(h), "encoding {v:?}");
            assert_eq!(&decode(&hex(h)).unwrap(), v, "decoding {h}");
        }
    }

    /// Longer forms: only the header bytes were printed by python (`.hex()[:12]`); the payload
    /// is the repeated byte, so the full literal is header + payload.
    #[test]
    fn sixteen_bit_forms_match_python_msgpack() {
        // b"\xab"*300 -> c5 012c ab...
        let bin = vec![0xab; 300];
        let mut want = hex("c5012c");
        want.extend_from_slice(&bin);
        assert_eq!(enc(&Value::Bin(&bin)), want);
        assert_eq!(decode(&want).unwrap(), Value::Bin(&bin));
        // "y"*300 -> da 012c 79...
        let s = "y".repeat(300);
        let mut want = hex("da012c");
        want.extend_from_slice(s.as_bytes());
        assert_eq!(enc(&Value::Str(&s)), want);
        // {i: i for i in range(16)} -> de 0010 00 00 01 01 ...
        let map = Value::Map((0..16).map(|i| (Value::Int(i), Value::Int(i))).collect());
        let mut want = hex("de0010");
        for i in 0..16u8 {
            want.extend_from_slice(&[i, i]);
        }
        assert_eq!(enc(&map), want);
        assert_eq!(decode(&want).unwrap(), map);
        // list(range(16)) -> dc 0010 00 01 02 ...
        let arr = Value::Array((0..16).map(Value::Int).collect());
        let mut want = hex("dc0010");
        want.extend(0..16u8);
        assert_eq!(enc(&arr), want);
        assert_eq!(decode(&want).unwrap(), arr);
    }

    /// python: `{"a": {"b": [1, 2.5, b"\x00"]}, "c": True}`
    #[test]
    fn nested_map_matches_python_msgpack() {
        let bytes = hex("82a16181a1629301cb4004000000000000c40100a163c3");
        let v = decode(&bytes).unwrap();
        let inner = v.get("a").unwrap();
        assert_eq!(
            inner.get("b"),
            Some(&Value::Array(vec![
                Value::Int(1),
                Value::Float(2.5),
                Value::Bin(&[0])
            ]))
        );
        assert_eq!(v.get("c"), Some(&Value::Bool(true)));
        assert_eq!(v.get("zz"), None);
        assert_eq!(Value::Int(1).get("a"), None);
        assert_eq!(enc(&v), bytes);
    }

    #[test]
    fn other_forms_decode() {
        // float 32: 0xca + IEEE single 1.5 = 3fc00000
        assert_eq!(decode(&hex("ca3fc00000")).unwrap(), Value::Float(1.5));
        // ext: fixext 1 (d4), type 5, payload 0x07; ext 8 (c7), length 3, type -1 (ff)
        assert_eq!(decode(&hex("d40507")).unwrap(), Value::Ext(5, &[7]));
        assert_eq!(
            decode(&hex("c703ff010203")).unwrap(),
            Value::Ext(-1, &[1, 2, 3])
        );
        assert_eq!(enc(&Value::Ext(-1, &[1, 2, 3])), hex("c703ff010203"));
        // str 16 / bin 32 / map 32 / array 32 with small contents
        assert_eq!(decode(&hex("da000141")).unwrap(), Value::Str("A"));
        assert_eq!(decode(&hex("c60000000142")).unwrap(), Value::Bin(&[0x42]));
        assert_eq!(
            decode(&hex("df00000001c0c3")).unwrap(),
            Value::Map(vec![(Value::Nil, Value::Bool(true))])
        );
        assert_eq!(
            decode(&hex("dd0000000107")).unwrap(),
            Value::Array(vec![Value::Int(7)])
        );
    }

    #[test]
    fn malformed_input_is_refused_with_a_reason() {
        assert!(malformed(&[]).contains("truncated"));
        assert!(malformed(&hex("cd01")).contains("truncated")); // uint16 missing a byte
        assert!(malformed(&hex("a36162")).contains("truncated")); // str of 3, 2 given
        assert!(malformed(&hex("c4ff00")).contains("truncated")); // bin of 255, 1 given
        assert!(malformed(&hex("c1")).contains("0xc1"));
        assert!(malformed(&hex("c0c0")).contains("trailing"));
        assert!(malformed(&hex("a2c328")).contains("str at offset 1")); // invalid UTF-8
        // a map announcing 2^32-1 entries in a 5-byte buffer is refused before allocating
        assert!(malformed(&hex("dfffffffff")).contains("announced"));
        assert!(malformed(&hex("ddffffffff")).contains("announced"));
        // nesting: 17 one-element arrays around nil is one level too deep
        let mut deep = vec![0x91; MAX_DEPTH + 1];
        deep.push(0xc0);
        assert!(malformed(&deep).contains("nesting"));
        deep.remove(0);
        assert!(decode(&deep).is_ok());
    }

    #[test]
    fn integers_beyond_msgpack_are_refused_on_encoding() {
        let mut out = Vec::new();
        assert!(encode(&Value::Int(u64::MAX as i128 + 1), &mut out).is_err());
        assert!(encode(&Value::Int(i64::MIN as i128 - 1), &mut out).is_err());
    }
}
