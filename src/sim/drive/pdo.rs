//! The twin drive's PDOs: RPDO1 applied at SYNC (synchronous types) or at once, TPDO1 sent
//! at SYNC or when its data changes (types 254/255), both carrying exactly the mapped
//! objects; and the EMCY producer.

use super::{TwinDrive, frame};
use crate::canopen::cia402::MODE_CSP;
use crate::canopen::emcy::Emcy;
use crate::canopen::pdo::COB_INVALID;
use crate::canopen::sdo::ObjAddr;
use crate::canopen::{NmtState, cob};
use std::time::Instant;

impl TwinDrive {
    pub(super) fn rpdo_cob(&self) -> Option<u32> {
        let c = self.od.u32(0x1400, 1);
        (c & COB_INVALID == 0).then_some(c & 0x7FF)
    }

    pub(super) fn tpdo_cob(&self) -> Option<u32> {
        let c = self.od.u32(0x1800, 1);
        (c & COB_INVALID == 0).then_some(c & 0x7FF)
    }

    pub(super) fn on_rpdo(&mut self, data: &[u8], now: Instant) {
        let need: usize = self
            .od
            .mapping(0x1600)
            .iter()
            .map(|e| e.bits as usize / 8)
            .sum();
        if data.len() < need {
            // CiA 301: PDO not processed due to length error.
            self.emcy(0x8210, [0; 5]);
            return;
        }
        if self.od.u8(0x1400, 2) <= 240 {
            self.rpdo_latched = Some(data.to_vec());
        } else {
            self.apply_rpdo(data, now);
        }
    }

    fn apply_rpdo(&mut self, data: &[u8], now: Instant) {
        let mut at = 0;
        let mut touched = Vec::new();
        for e in self.od.mapping(0x1600) {
            let n = e.bits as usize / 8;
            self.od.set(e.index, e.sub, &data[at..at + n]);
            touched.push(e.index);
            at += n;
        }
        // Mode first, then the controlword (which may start a set-point with the new target),
        // then in CSP the target as the new demand.
        if touched.contains(&0x6060) {
            self.on_mode(now);
        }
        if touched.contains(&0x6040) {
            let cw = self.od.u16(0x6040, 0);
            self.on_controlword(cw, now);
        }
        if touched.contains(&0x607A) && self.mode() == MODE_CSP {
            self.take_demand(now);
        }
    }

    fn tpdo_data(&mut self) -> Vec<u8> {
        self.refresh_od();
        let mut d = Vec::with_capacity(8);
        for e in self.od.mapping(0x1A00) {
            if let Ok(v) = self.od.read(ObjAddr::new(e.index, e.sub)) {
                d.extend_from_slice(&v);
            }
        }
        d
    }

    fn send_tpdo(&mut self, cob_id: u32) {
        let d = self.tpdo_data();
        self.tx.push_back(frame(cob_id as u16, &d));
        self.last_tpdo = Some(d);
    }

    pub(super) fn on_sync(&mut self, now: Instant) {
        if self.nmt != NmtState::Operational {
            return;
        }
        if let Some(d) = self.rpdo_latched.take() {
            self.apply_rpdo(&d, now);
        }
        self.update(now);
        if let Some(cob_id) = self.tpdo_cob() {
            let ty = self.od.u8(0x1800, 2);
            if ty == 0 {
                self.send_tpdo(cob_id);
            } else if ty <= 240 {
                self.tpdo_syncs += 1;
                if self.tpdo_syncs >= ty as u16 {
                    self.tpdo_syncs = 0;
                    self.send_tpdo(cob_id);
                }
            }
        }
    }

    /// Event-driven TPDO (types 254/255): sent when its data changes.
    pub(super) fn event_tpdo(&mut self) {
        if self.nmt != NmtState::Operational {
            return;
        }
        if let Some(cob_id) = self.tpdo_cob()
            && self.od.u8(0x1800, 2) >= 254
        {
            let d = self.tpdo_data();
            if self.last_tpdo.as_ref() != Some(&d) {
                self.send_tpdo(cob_id);
            }
        }
    }

    pub(super) fn emcy(&mut self, code: u16, manufacturer: [u8; 5]) {
        if self.nmt == NmtState::Stopped {
            return;
        }
        let register = self.od.u8(0x1001, 0);
        let e = Emcy {
            code,
            register,
            manufacturer,
        };
        self.tx.push_back(frame(cob::EMCY + self.id(), &e.encode()));
    }
}
