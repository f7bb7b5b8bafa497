//! The twin drive's SDO server (expedited and segmented, any length), refusals and delays as
//! injected, and the rules of writing an object: access and length, the PDO communication
//! and mapping rules, valid modes of operation, and what a write sets off.

use super::od::Pdo;
use super::{Transfer, TwinDrive, frame};
use crate::canopen::cia402::{MODE_CSP, MODE_HOMING, MODE_PROFILE_POSITION};
use crate::canopen::pdo::{COB_INVALID, MapEntry};
use crate::canopen::sdo::{AbortCode, ObjAddr, encode_abort};
use crate::canopen::{NmtState, cob};
use canopen_rs::sdo as codec;
use std::time::Instant;

impl TwinDrive {
    fn respond(&mut self, p: [u8; 8], now: Instant) {
        let f = frame(cob::SDO_TX + self.id(), &p);
        if self.sdo_delay.is_zero() {
            self.tx.push_back(f);
        } else {
            self.delayed.push_back((now + self.sdo_delay, f));
        }
    }

    fn abort(&mut self, obj: ObjAddr, code: AbortCode, now: Instant) {
        self.transfer = None;
        self.respond(encode_abort(obj, code), now);
    }

    pub(super) fn on_sdo(&mut self, data: &[u8], now: Instant) {
        if self.nmt == NmtState::Stopped || data.is_empty() {
            return;
        }
        let mut p = [0u8; 8];
        p[..data.len().min(8)].copy_from_slice(&data[..data.len().min(8)]);
        let mux = ObjAddr::from_frame(&p);
        let cs = p[0] >> 5;
        let current = match self.transfer {
            Some(Transfer::Upload { obj, .. } | Transfer::Download { obj, .. }) => Some(obj),
            None => None,
        };
        if cs == 4 {
            // The client aborts: no answer.
            self.transfer = None;
            return;
        }
        if let Some(r) = self.refusal {
            let obj = if matches!(cs, 1 | 2) {
                mux
            } else {
                current.unwrap_or(mux)
            };
            if r.index.is_none_or(|i| i == obj.index) {
                return self.abort(obj, r.code, now);
            }
        }
        match cs {
            1 => self.sdo_download_initiate(mux, &p, now),
            0 => self.sdo_download_segment(&p, now),
            2 => self.sdo_upload_initiate(mux, now),
            3 => self.sdo_upload_segment(&p, now),
            _ => self.abort(current.unwrap_or(mux), AbortCode::COMMAND_INVALID, now),
        }
    }

    fn sdo_download_initiate(&mut self, obj: ObjAddr, p: &[u8; 8], now: Instant) {
        self.transfer = None;
        let expedited = p[0] & 0x02 != 0;
        let sized = p[0] & 0x01 != 0;
        if expedited {
            let len = if sized {
                4 - ((p[0] >> 2) & 0x03) as usize
            } else {
                // Size not indicated: the object's own size, at most 4.
                self.od.entry(obj).map_or(4, |e| e.size.unwrap_or(4).min(4))
            };
            match self.write_object(obj, &p[4..4 + len], now) {
                Ok(()) => self.respond(codec::encode_download_response(addr(obj)), now),
                Err(code) => self.abort(obj, code, now),
            }
            return;
        }
        let size = sized.then(|| u32::from_le_bytes([p[4], p[5], p[6], p[7]]) as usize);
        // Check what can be checked before the data arrives.
        let check = match size {
            Some(n) => self.od.check_write(obj, n),
            None => self.od.check_write(obj, 0).or_else(|c| {
                if c == AbortCode::LENGTH_TOO_LOW {
                    Ok(())
                } else {
                    Err(c)
                }
            }),
        };
        if let Err(code) = check {
            return self.abort(obj, code, now);
        }
        self.buf.clear();
        self.transfer = Some(Transfer::Download {
            obj,
            size,
            toggle: false,
        });
        self.respond(codec::encode_download_response(addr(obj)), now);
    }

    fn sdo_download_segment(&mut self, p: &[u8; 8], now: Instant) {
        let Some(Transfer::Download { obj, size, toggle }) = self.transfer else {
            return self.abort(ObjAddr::new(0, 0), AbortCode::COMMAND_INVALID, now);
        };
        let Ok(seg) = codec::decode_data_segment(p) else {
            return self.abort(obj, AbortCode::COMMAND_INVALID, now);
        };
        if seg.toggle != toggle {
            return self.abort(obj, AbortCode::TOGGLE_NOT_ALTERNATED, now);
        }
        self.buf.extend_from_slice(seg.data);
        if !seg.last {
            self.transfer = Some(Transfer::Download {
                obj,
                size,
                toggle: !toggle,
            });
            return self.respond(codec::encode_download_segment_response(toggle), now);
        }
        self.transfer = None;
        if size.is_some_and(|n| n != self.buf.len()) {
            return self.abort(obj, AbortCode::LENGTH_MISMATCH, now);
        }
        let data = std::mem::take(&mut self.buf);
        match self.write_object(obj, &data, now) {
            Ok(()) => self.respond(codec::encode_download_segment_response(toggle), now),
            Err(code) => self.abort(obj, code, now),
        }
    }

    fn sdo_upload_initiate(&mut self, obj: ObjAddr, now: Instant) {
        self.transfer = None;
        self.refresh_od();
        let data = match self.od.read(obj) {
            Ok(d) => d,
            Err(code) => return self.abort(obj, code, now),
        };
        if (1..=4).contains(&data.len()) {
            // Expedited: scs 2, n = 4 − len unused bytes, e = 1, s = 1; data in bytes 4–7.
            let mut p = [0u8; 8];
            p[0] = 0x43 | (((4 - data.len()) as u8) << 2);
            p[1..3].copy_from_slice(&obj.index.to_le_bytes());
            p[3] = obj.sub;
            p[4..4 + data.len()].copy_from_slice(&data);
            return self.respond(p, now);
        }
        self.respond(
            codec::encode_upload_initiate_segmented_response(addr(obj), data.len() as u32),
            now,
        );
        self.buf = data;
        self.transfer = Some(Transfer::Upload {
            obj,
            pos: 0,
            toggle: false,
        });
    }

    fn sdo_upload_segment(&mut self, p: &[u8; 8], now: Instant) {
        let Some(Transfer::Upload { obj, pos, toggle }) = self.transfer else {
            return self.abort(ObjAddr::new(0, 0), AbortCode::COMMAND_INVALID, now);
        };
        if (p[0] & 0x10 != 0) != toggle {
            return self.abort(obj, AbortCode::TOGGLE_NOT_ALTERNATED, now);
        }
        let end = (pos + codec::SEGMENT_DATA_MAX).min(self.buf.len());
        let last = end == self.buf.len();
        let Ok(seg) = codec::encode_data_segment(&self.buf[pos..end], toggle, last) else {
            return self.abort(obj, AbortCode::GENERAL, now);
        };
        self.transfer = (!last).then_some(Transfer::Upload {
            obj,
            pos: end,
            toggle: !toggle,
        });
        self.respond(seg, now);
    }

    /// Write an object through the SDO server: access, length and the object's own rules.
    fn write_object(&mut self, obj: ObjAddr, data: &[u8], now: Instant) -> Result<(), AbortCode> {
        self.od.check_write(obj, data.len())?;
        let u32v = || {
            let mut b = [0u8; 4];
            b[..data.len().min(4)].copy_from_slice(&data[..data.len().min(4)]);
            u32::from_le_bytes(b)
        };
        match (obj.index, obj.sub) {
            (0x1400 | 0x1800, 1) => {
                let cur = self.od.u32(obj.index, 1);
                let new = u32v();
                if cur & COB_INVALID == 0 && new & COB_INVALID == 0 && new != cur {
                    return Err(AbortCode::INVALID_VALUE);
                }
            }
            (0x1600 | 0x1A00, sub) => {
                let comm = obj.index - 0x200;
                if self.od.u32(comm, 1) & COB_INVALID == 0 {
                    return Err(AbortCode::DEVICE_STATE);
                }
                if sub == 0 {
                    self.check_mapping(obj.index, data.first().copied().unwrap_or(0))?;
                } else if self.od.u8(obj.index, 0) != 0 {
                    return Err(AbortCode::DEVICE_STATE);
                }
            }
            (0x6060, 0)
                if !matches!(
                    data[0] as i8,
                    0 | MODE_PROFILE_POSITION | MODE_HOMING | MODE_CSP
                ) =>
            {
                return Err(AbortCode::INVALID_VALUE);
            }
            _ => {}
        }
        self.od.set(obj.index, obj.sub, data);
        self.after_write(obj.index, now);
        Ok(())
    }

    /// Enabling `n` entries of mapping `map_index`: each must name a mappable object of the
    /// right direction with its exact length, and all together fit 64 bits.
    fn check_mapping(&self, map_index: u16, n: u8) -> Result<(), AbortCode> {
        if n > 8 {
            return Err(AbortCode::VALUE_TOO_HIGH);
        }
        let want = if map_index == 0x1600 {
            Pdo::Rx
        } else {
            Pdo::Tx
        };
        let mut bits = 0u32;
        for k in 1..=n {
            let e = MapEntry::decode(self.od.u32(map_index, k));
            let entry = self
                .od
                .entry(ObjAddr::new(e.index, e.sub))
                .map_err(|_| AbortCode::NOT_MAPPABLE)?;
            if entry.pdo != want || entry.size.map(|s| s * 8) != Some(e.bits as usize) {
                return Err(AbortCode::NOT_MAPPABLE);
            }
            bits += e.bits as u32;
        }
        if bits > 64 {
            return Err(AbortCode::PDO_TOO_LONG);
        }
        Ok(())
    }

    fn after_write(&mut self, index: u16, now: Instant) {
        match index {
            0x1017 => self.schedule_heartbeat(now),
            0x6040 => {
                let cw = self.od.u16(0x6040, 0);
                self.on_controlword(cw, now);
            }
            0x6060 => self.on_mode(now),
            _ => {}
        }
    }
}

fn addr(obj: ObjAddr) -> canopen_rs::Address {
    canopen_rs::Address::new(obj.index, obj.sub)
}
