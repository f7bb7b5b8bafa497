//! Registers → volts → spot, per map and mode (pure functions), and the inverse the twin's
//! I/O module uses to serve a plant sample as counts.
//!
//! Conditioned: `x = gain_x · V_X + offset_x`, `y = gain_y · V_Y + offset_y`, SUM = `V_SUM`.
//! Electrodes (Hamamatsu formulas (3-1)..(3-4), duo- and tetra-lateral alike):
//! `x = Lx/2 · (V_X2 − V_X1)/(V_X1 + V_X2)`, `y = Ly/2 · (V_Y2 − V_Y1)/(V_Y1 + V_Y2)`,
//! SUM = `V_X1 + V_X2 + V_Y1 + V_Y2`.
//! A PSD whose SUM is below the map's threshold, or whose electrode pair sums are not
//! positive, has no spot: the frame is invalid and is never averaged in.

use super::Frame;
use super::map::{Channel, IoMap, PsdMap};
use crate::modbus::codec::CodecError;
use crate::optics::Spot;
use std::time::Instant;
use thiserror::Error;

/// Why a block could not be decoded or encoded.
#[derive(Clone, Copy, Debug, Error, PartialEq)]
pub enum DecodeError {
    #[error("the block has {got} registers, the map needs {expected}")]
    Length { expected: usize, got: usize },
    #[error("PSD{psd} {signal}: {source}")]
    Codec {
        psd: usize,
        signal: &'static str,
        source: CodecError,
    },
    #[error("PSD{psd} {signal} is not a finite number (a float register holding NaN or infinity)")]
    NotFinite { psd: usize, signal: &'static str },
}

/// Three spots and SUMs from one block.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reading {
    pub spots: [Option<Spot>; 3],
    pub sums: [f64; 3],
}

fn volts(c: &Channel, block: &[u16], psd: usize, signal: &'static str) -> Result<f64, DecodeError> {
    let v = c.volts(block).map_err(|source| DecodeError::Codec {
        psd: psd + 1,
        signal,
        source,
    })?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(DecodeError::NotFinite {
            psd: psd + 1,
            signal,
        })
    }
}

/// Decode the block read for `map` (registers from the block start).
pub fn decode(map: &IoMap, block: &[u16]) -> Result<Reading, DecodeError> {
    if block.len() != map.block_len() {
        return Err(DecodeError::Length {
            expected: map.block_len(),
            got: block.len(),
        });
    }
    let mut spots = [None; 3];
    let mut sums = [0.0; 3];
    for (k, psd) in map.psds.iter().enumerate() {
        let (spot, sum) = match psd {
            PsdMap::Conditioned(c) => {
                let vx = volts(&c.x, block, k, "X")?;
                let vy = volts(&c.y, block, k, "Y")?;
                let vs = volts(&c.sum, block, k, "SUM")?;
                let spot = Spot {
                    x: c.gain_x_mm_per_v * vx + c.offset_x_mm,
                    y: c.gain_y_mm_per_v * vy + c.offset_y_mm,
                };
                (spot_if(vs >= map.sum_threshold_v, spot), vs)
            }
            PsdMap::Electrodes(e) => {
                let x1 = volts(&e.x1, block, k, "X1")?;
                let x2 = volts(&e.x2, block, k, "X2")?;
                let y1 = volts(&e.y1, block, k, "Y1")?;
                let y2 = volts(&e.y2, block, k, "Y2")?;
                let (sx, sy) = (x1 + x2, y1 + y2);
                let sum = sx + sy;
                let lit = sum >= map.sum_threshold_v && sx > 0.0 && sy > 0.0;
                let spot = if lit {
                    Spot {
                        x: e.length_x_mm / 2.0 * (x2 - x1) / sx,
                        y: e.length_y_mm / 2.0 * (y2 - y1) / sy,
                    }
                } else {
                    Spot { x: 0.0, y: 0.0 }
                };
                (spot_if(lit, spot), sum)
            }
        };
        spots[k] = spot;
        sums[k] = sum;
    }
    Ok(Reading { spots, sums })
}

fn spot_if(lit: bool, s: Spot) -> Option<Spot> {
    lit.then_some(s)
}

/// A [`Frame`] from a block read that arrived at `at` (`unix_us` the same instant on the wall
/// clock).
pub fn frame(
    map: &IoMap,
    block: &[u16],
    seq: u64,
    at: Instant,
    unix_us: i64,
) -> Result<Frame, DecodeError> {
    let r = decode(map, block)?;
    Ok(Frame {
        seq,
        at,
        unix_us,
        spots: r.spots,
        sums: r.sums,
    })
}

/// The block a module following `map` would present for these spots and SUMs (the inverse
/// of [`decode`], for the twin). A PSD without a spot reads as centred (X = Y = 0) with its
/// SUM; in electrode mode each axis' pair carries half the SUM. Values beyond a channel's
/// range saturate like an ADC; registers no channel uses (status words, spares) are 0.
pub fn encode(map: &IoMap, reading: &Reading) -> Result<Vec<u16>, DecodeError> {
    let mut block = vec![0u16; map.block_len()];
    for (k, psd) in map.psds.iter().enumerate() {
        let spot = reading.spots[k].unwrap_or(Spot { x: 0.0, y: 0.0 });
        let sum = reading.sums[k];
        let mut put = |c: &Channel, v: f64, signal: &'static str| {
            c.put_volts(v, &mut block)
                .map_err(|source| DecodeError::Codec {
                    psd: k + 1,
                    signal,
                    source,
                })
        };
        match psd {
            PsdMap::Conditioned(c) => {
                put(&c.x, (spot.x - c.offset_x_mm) / c.gain_x_mm_per_v, "X")?;
                put(&c.y, (spot.y - c.offset_y_mm) / c.gain_y_mm_per_v, "Y")?;
                put(&c.sum, sum, "SUM")?;
            }
            PsdMap::Electrodes(e) => {
                let half = sum / 2.0;
                let ux = 2.0 * spot.x / e.length_x_mm;
                let uy = 2.0 * spot.y / e.length_y_mm;
                put(&e.x1, half / 2.0 * (1.0 - ux), "X1")?;
                put(&e.x2, half / 2.0 * (1.0 + ux), "X2")?;
                put(&e.y1, half / 2.0 * (1.0 - uy), "Y1")?;
                put(&e.y2, half / 2.0 * (1.0 + uy), "Y2")?;
            }
        }
    }
    Ok(block)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::codec::{self as c, ValueType, WordOrder};

    fn conditioned(channels: &str, block_length: u16, defaults: &str) -> IoMap {
        let text = format!(
            r#"
name = "t"
register = "holding"
unit_id = 7
block_start = 100
block_length = {block_length}
mode = "conditioned"
sum_threshold_v = 0.5
[defaults]
{defaults}
{channels}
"#
        );
        IoMap::parse(&text, "test.toml").unwrap_or_else(|e| panic!("{e}"))
    }

    fn psd(x: u16, y: u16, s: u16, gain: f64, off: f64) -> String {
        format!(
            "[[psd]]\ngain_x_mm_per_v = {gain}\ngain_y_mm_per_v = {gain}\noffset_x_mm = {off}\noffset_y_mm = {off}\nx = {{ register = {x} }}\ny = {{ register = {y} }}\nsum = {{ register = {s} }}\n"
        )
    }

    #[test]
    fn generic_map_hand_computed() {
        let map = IoMap::generic().unwrap();
        // PSD1: X = 3277 counts = 1.0000916 V → 1.0000916 mm; Y = -6554 → -2.0001831 mm;
        // SUM 16384 = 5.0001526 V. PSD2 SUM 100 counts = 0.0305 V: below 0.5 V, no spot.
        // PSD3: X = 0x8001 = -32767 → -10 V.
        let regs = [3277, (-6554i16) as u16, 16384, 1, 2, 100, 0x8001, 0, 16384];
        let r = decode(&map, &regs).unwrap();
        let v = 10.0 / 32767.0;
        let s1 = r.spots[0].unwrap();
        assert!((s1.x - 3277.0 * v).abs() < 1e-12 && (s1.x - 1.0000916).abs() < 1e-7);
        assert!((s1.y + 6554.0 * v).abs() < 1e-12);
        assert!((r.sums[0] - 16384.0 * v).abs() < 1e-12);
        assert_eq!(r.spots[1], None);
        assert!((r.sums[1] - 0.030518509).abs() < 1e-9);
        assert!((r.spots[2].unwrap().x + 10.0).abs() < 1e-12);
        assert_eq!(
            decode(&map, &regs[..8]),
            Err(DecodeError::Length {
                expected: 9,
                got: 8
            })
        );
    }

    #[test]
    fn conditioned_gain_offset_every_type_and_order() {
        // Each PSD's X, Y, SUM as `ty` in `order`; scale 0.001 V/count, offset 0.25 V.
        for ty in ValueType::ALL {
            for order in WordOrder::ALL {
                let w = ty.words();
                let chans = (0..3)
                    .map(|k| psd(3 * k * w, (3 * k + 1) * w, (3 * k + 2) * w, 2.5, -0.5))
                    .collect::<String>();
                let defaults = format!(
                    "type = \"{ty}\"\nword_order = \"{order}\"\nvolts_per_count = 0.001\nvolts_offset = 0.25\n"
                );
                let map = conditioned(&chans, 9 * w, &defaults);
                let counts = [1000.0, 2000.0, 4750.0, 0.0, 500.0, 100.0, 3.0, 7.0, 9999.0];
                let mut regs = vec![0u16; 9 * w as usize];
                for (i, n) in counts.iter().enumerate() {
                    c::encode(ty, order, *n, &mut regs[i * w as usize..]).unwrap();
                }
                let r = decode(&map, &regs).unwrap();
                // PSD1: V_X = 1.25 V → 2.5·1.25 − 0.5 = 2.625 mm; V_Y = 2.25 → 5.125 mm;
                // SUM = 5.0 V.
                let s = r.spots[0].unwrap_or_else(|| panic!("{ty} {order}"));
                assert!((s.x - 2.625).abs() < 1e-9, "{ty} {order}: {}", s.x);
                assert!((s.y - 5.125).abs() < 1e-9, "{ty} {order}");
                assert!((r.sums[0] - 5.0).abs() < 1e-9);
                // PSD2: SUM 0.35 V < 0.5 V: no spot.
                assert_eq!(r.spots[1], None, "{ty} {order}");
                assert!((r.sums[1] - 0.35).abs() < 1e-9);
                // PSD3: V_X = 0.253 → 0.1325 mm; V_Y = 0.257 → 0.1425 mm; SUM 10.249 V.
                let s = r.spots[2].unwrap();
                assert!((s.x - 0.1325).abs() < 1e-9 && (s.y - 0.1425).abs() < 1e-9);
                // The inverse puts the same counts back.
                assert_eq!(
                    encode(&map, &r).unwrap()[..3 * w as usize],
                    regs[..3 * w as usize]
                );
            }
        }
    }

    #[test]
    fn signed_counts_below_zero() {
        let chans = psd(0, 1, 2, 1.0, 0.0) + &psd(3, 4, 5, 1.0, 0.0) + &psd(6, 7, 8, 1.0, 0.0);
        let map = conditioned(&chans, 9, "type = \"i16\"\nvolts_per_count = 0.001\n");
        let mut regs = vec![5000u16; 9];
        regs[0] = (-1234i16) as u16; // 0xFB2E
        assert_eq!(regs[0], 0xFB2E);
        let r = decode(&map, &regs).unwrap();
        assert!((r.spots[0].unwrap().x + 1.234).abs() < 1e-12);
        // The same register as u16 is 64302 counts.
        let map = conditioned(&chans, 9, "type = \"u16\"\nvolts_per_count = 0.001\n");
        assert!((decode(&map, &regs).unwrap().spots[0].unwrap().x - 64.302).abs() < 1e-9);
    }

    #[test]
    fn float_nan_is_an_error_not_a_spot() {
        let chans = psd(0, 2, 4, 1.0, 0.0) + &psd(6, 8, 10, 1.0, 0.0) + &psd(12, 14, 16, 1.0, 0.0);
        let map = conditioned(&chans, 18, "type = \"f32\"\nvolts_per_count = 1.0\n");
        let mut regs = vec![0u16; 18];
        regs[8..10].copy_from_slice(&c::f32_to_regs(f32::NAN, WordOrder::Abcd));
        assert_eq!(
            decode(&map, &regs),
            Err(DecodeError::NotFinite {
                psd: 2,
                signal: "Y"
            })
        );
    }

    fn electrodes(layout: &str) -> IoMap {
        let mut t = String::from(
            "name = \"e\"\nregister = \"input\"\nunit_id = 1\nblock_start = 0\nblock_length = 12\nmode = \"electrodes\"\nsum_threshold_v = 0.5\n[defaults]\ntype = \"u16\"\nvolts_per_count = 0.001\n",
        );
        for k in 0..3 {
            t += &format!(
                "[[psd]]\nlayout = \"{layout}\"\nlength_x_mm = 10.0\nlength_y_mm = 8.0\nx1 = {{ register = {} }}\nx2 = {{ register = {} }}\ny1 = {{ register = {} }}\ny2 = {{ register = {} }}\n",
                4 * k,
                4 * k + 1,
                4 * k + 2,
                4 * k + 3
            );
        }
        IoMap::parse(&t, "e.toml").unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn electrode_formulas_hand_computed() {
        for layout in ["duo-lateral", "tetra-lateral"] {
            let map = electrodes(layout);
            // PSD1: X1 = 1.0 V, X2 = 3.0 V → x = 5 · 2/4 = 2.5 mm;
            //       Y1 = 2.5 V, Y2 = 1.5 V → y = 4 · (−1)/4 = −1.0 mm; SUM = 8 V.
            // PSD2: all 0.1 V → SUM 0.4 V < 0.5 V: no spot.
            // PSD3: X pair 0/0 with the Y pair lit → no spot (cannot divide).
            let regs = [1000, 3000, 2500, 1500, 100, 100, 100, 100, 0, 0, 400, 900];
            let r = decode(&map, &regs).unwrap();
            let s = r.spots[0].unwrap();
            assert!((s.x - 2.5).abs() < 1e-12, "{layout}");
            assert!((s.y + 1.0).abs() < 1e-12, "{layout}");
            assert!((r.sums[0] - 8.0).abs() < 1e-12);
            assert_eq!(r.spots[1], None);
            assert!((r.sums[1] - 0.4).abs() < 1e-12);
            assert_eq!(r.spots[2], None);
            assert!((r.sums[2] - 1.3).abs() < 1e-12);
        }
    }

    #[test]
    fn electrode_encode_decode_round_trip() {
        let map = electrodes("tetra-lateral");
        let reading = Reading {
            spots: [
                Some(Spot { x: 1.2, y: -3.1 }),
                None,
                Some(Spot { x: -4.9, y: 3.9 }),
            ],
            sums: [5.0, 0.02, 6.0],
        };
        let block = encode(&map, &reading).unwrap();
        // PSD1: pair sums 2.5 V; X2 = 1.25 · (1 + 0.24) = 1.55 V = 1550 counts.
        assert_eq!(block[1], 1550);
        assert_eq!(block[0], 950);
        let back = decode(&map, &block).unwrap();
        // Quantisation: 1 mV per count on electrodes carrying ~1.25 V → ≤ Lx/2 · 1e-3/2.5.
        for k in [0, 2] {
            let (a, b) = (back.spots[k].unwrap(), reading.spots[k].unwrap());
            assert!((a.x - b.x).abs() < 5.0 * 1e-3 / 2.5 + 1e-12, "{k}");
            assert!((a.y - b.y).abs() < 4.0 * 1e-3 / 2.5 + 1e-12, "{k}");
        }
        assert_eq!(back.spots[1], None);
    }

    #[test]
    fn shipped_product_maps_round_trip() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/io");
        for file in ["wago-750-352-750-456.toml", "beckhoff-bk9000-kl3404.toml"] {
            let map = IoMap::load(&root.join(file)).unwrap();
            let reading = Reading {
                spots: [
                    Some(Spot { x: 0.5, y: -0.25 }),
                    Some(Spot { x: -2.0, y: 1.0 }),
                    None,
                ],
                sums: [5.0, 4.0, 0.02],
            };
            let block = encode(&map, &reading).unwrap();
            let back = decode(&map, &block).unwrap();
            for k in 0..2 {
                let (a, b) = (back.spots[k].unwrap(), reading.spots[k].unwrap());
                assert!(
                    (a.x - b.x).abs() < 5e-3 && (a.y - b.y).abs() < 5e-3,
                    "{file}"
                );
                assert!((back.sums[k] - reading.sums[k]).abs() < 5e-3, "{file}");
            }
            assert_eq!(back.spots[2], None, "{file}");
        }
        // WAGO: PSD1 X = 0.5 V → 1638.4 counts → 1638 → 1632 with the status bits clear.
        let wago = IoMap::load(&root.join("wago-750-352-750-456.toml")).unwrap();
        let r = Reading {
            spots: [Some(Spot { x: 0.5, y: 0.0 }), None, None],
            sums: [5.0, 0.0, 0.0],
        };
        let b = encode(&wago, &r).unwrap();
        assert_eq!((b[0], b[6]), (1632, 0x4000));
        // Beckhoff: status words stay 0; PSD1 X2 = 1.25 · (1 + 0.5/4.5) V at register 3.
        let bk = IoMap::load(&root.join("beckhoff-bk9000-kl3404.toml")).unwrap();
        let b = encode(&bk, &r).unwrap();
        assert_eq!(b[0], 0);
        let want = (1.25f64 * (1.0 + 1.0 / 9.0) / (10.0 / 32767.0)).round() as u16;
        assert_eq!(b[3], want);
    }
}
