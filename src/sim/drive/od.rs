//! The twin drive's object dictionary: entries with their access, size and PDO direction,
//! typed reads, checked writes; the communication objects (reset by NMT reset
//! communication) and the CiA 301/402 objects the master uses.

use super::TwinDriveConfig;
use crate::canopen::pdo::MapEntry;
use crate::canopen::sdo::{AbortCode, ObjAddr};
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Access {
    Ro,
    Rw,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Pdo {
    No,
    /// May be mapped into an RPDO (written by the master).
    Rx,
    /// May be mapped into a TPDO (read by the master).
    Tx,
}

#[derive(Clone, Debug)]
pub(super) struct Entry {
    data: Vec<u8>,
    access: Access,
    /// `None`: variable length up to `max`.
    pub(super) size: Option<usize>,
    max: usize,
    pub(super) pdo: Pdo,
}

#[derive(Clone, Debug, Default)]
pub(super) struct Od {
    map: BTreeMap<(u16, u8), Entry>,
}

impl Od {
    fn add(&mut self, index: u16, sub: u8, data: Vec<u8>, access: Access, pdo: Pdo) {
        let size = Some(data.len());
        self.map.insert(
            (index, sub),
            Entry {
                max: data.len(),
                data,
                access,
                size,
                pdo,
            },
        );
    }
    fn add_var(&mut self, index: u16, sub: u8, data: Vec<u8>, max: usize, access: Access) {
        self.map.insert(
            (index, sub),
            Entry {
                data,
                access,
                size: None,
                max,
                pdo: Pdo::No,
            },
        );
    }
    pub(super) fn entry(&self, obj: ObjAddr) -> Result<&Entry, AbortCode> {
        match self.map.get(&(obj.index, obj.sub)) {
            Some(e) => Ok(e),
            None if self.map.keys().any(|(i, _)| *i == obj.index) => Err(AbortCode::NO_SUBINDEX),
            None => Err(AbortCode::NO_OBJECT),
        }
    }
    pub(super) fn read(&self, obj: ObjAddr) -> Result<Vec<u8>, AbortCode> {
        self.entry(obj).map(|e| e.data.clone())
    }
    /// Existence, access and length of a write of `len` bytes.
    pub(super) fn check_write(&self, obj: ObjAddr, len: usize) -> Result<(), AbortCode> {
        let e = self.entry(obj)?;
        if e.access != Access::Rw {
            return Err(AbortCode::WRITE_OF_READ_ONLY);
        }
        match e.size {
            Some(n) if len > n => Err(AbortCode::LENGTH_TOO_HIGH),
            Some(n) if len < n => Err(AbortCode::LENGTH_TOO_LOW),
            None if len > e.max => Err(AbortCode::LENGTH_TOO_HIGH),
            _ => Ok(()),
        }
    }
    /// Store without checks (internal values, PDO data already checked).
    pub(super) fn set(&mut self, index: u16, sub: u8, data: &[u8]) {
        if let Some(e) = self.map.get_mut(&(index, sub)) {
            e.data = data.to_vec();
        }
    }
    fn uint(&self, index: u16, sub: u8) -> u64 {
        self.map.get(&(index, sub)).map_or(0, |e| {
            e.data
                .iter()
                .take(8)
                .rev()
                .fold(0u64, |acc, &b| (acc << 8) | b as u64)
        })
    }
    pub(super) fn u8(&self, index: u16, sub: u8) -> u8 {
        self.uint(index, sub) as u8
    }
    pub(super) fn u16(&self, index: u16, sub: u8) -> u16 {
        self.uint(index, sub) as u16
    }
    pub(super) fn u32(&self, index: u16, sub: u8) -> u32 {
        self.uint(index, sub) as u32
    }
    pub(super) fn i32(&self, index: u16, sub: u8) -> i32 {
        self.u32(index, sub) as i32
    }
    pub(super) fn i8(&self, index: u16, sub: u8) -> i8 {
        self.u8(index, sub) as i8
    }
    pub(super) fn mapping(&self, map_index: u16) -> Vec<MapEntry> {
        let n = self.u8(map_index, 0).min(8);
        (1..=n)
            .map(|k| MapEntry::decode(self.u32(map_index, k)))
            .collect()
    }
}

/// The communication objects (reset by NMT reset communication).
pub(super) fn communication_objects(od: &mut Od, node: u8, heartbeat_ms: u16) {
    let id = node as u32;
    od.add(
        0x1017,
        0,
        heartbeat_ms.to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    od.add(0x1400, 0, vec![2], Access::Ro, Pdo::No);
    od.add(
        0x1400,
        1,
        (0x200 + id).to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    od.add(0x1400, 2, vec![255], Access::Rw, Pdo::No);
    od.add(0x1600, 0, vec![1], Access::Rw, Pdo::No);
    od.add(
        0x1600,
        1,
        0x6040_0010u32.to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    for k in 2..=8 {
        od.add(0x1600, k, vec![0; 4], Access::Rw, Pdo::No);
    }
    od.add(0x1800, 0, vec![5], Access::Ro, Pdo::No);
    od.add(
        0x1800,
        1,
        (0x180 + id).to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    od.add(0x1800, 2, vec![255], Access::Rw, Pdo::No);
    od.add(0x1800, 3, vec![0; 2], Access::Rw, Pdo::No);
    od.add(0x1800, 5, vec![0; 2], Access::Rw, Pdo::No);
    od.add(0x1A00, 0, vec![1], Access::Rw, Pdo::No);
    od.add(
        0x1A00,
        1,
        0x6041_0010u32.to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    for k in 2..=8 {
        od.add(0x1A00, k, vec![0; 4], Access::Rw, Pdo::No);
    }
}

/// The device name (0x1008): longer than 32 bytes, so reading it needs a segmented upload
/// beyond canopen-rs's limit.
pub const DEVICE_NAME: &str = "axiscomp twin follower drive (CiA 402 servo: profile position, homing, cyclic synchronous position)";

pub(super) fn build_od(cfg: &TwinDriveConfig, cpm: f64) -> Od {
    let mut od = Od::default();
    let c = |mm: f64| ((mm * cpm).round().max(0.0) as u32).to_le_bytes().to_vec();
    od.add(
        0x1000,
        0,
        0x0002_0192u32.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(0x1001, 0, vec![0], Access::Ro, Pdo::Tx);
    od.add(
        0x1008,
        0,
        DEVICE_NAME.as_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(0x1018, 0, vec![4], Access::Ro, Pdo::No);
    for (k, v) in [
        (1u8, 0x0000_0A5Cu32),
        (2, 0x0000_402F),
        (3, 0x0001_0000),
        (4, 1),
    ] {
        od.add(0x1018, k, v.to_le_bytes().to_vec(), Access::Ro, Pdo::No);
    }
    communication_objects(&mut od, cfg.node_id, cfg.default_heartbeat_ms);
    od.add_var(0x2000, 0, Vec::new(), 256, Access::Rw);
    od.add(0x603F, 0, vec![0; 2], Access::Ro, Pdo::Tx);
    od.add(0x6040, 0, vec![0; 2], Access::Rw, Pdo::Rx);
    od.add(0x6041, 0, vec![0; 2], Access::Ro, Pdo::Tx);
    od.add(0x605A, 0, 2i16.to_le_bytes().to_vec(), Access::Rw, Pdo::No);
    od.add(0x6060, 0, vec![0], Access::Rw, Pdo::Rx);
    od.add(0x6061, 0, vec![0], Access::Ro, Pdo::Tx);
    od.add(0x6062, 0, vec![0; 4], Access::Ro, Pdo::Tx);
    od.add(0x6064, 0, vec![0; 4], Access::Ro, Pdo::Tx);
    od.add(0x6065, 0, c(0.5), Access::Rw, Pdo::No);
    od.add(0x6067, 0, c(0.001), Access::Rw, Pdo::No);
    od.add(0x606C, 0, vec![0; 4], Access::Ro, Pdo::Tx);
    od.add(0x607A, 0, vec![0; 4], Access::Rw, Pdo::Rx);
    od.add(0x607C, 0, vec![0; 4], Access::Rw, Pdo::No);
    od.add(0x607D, 0, vec![2], Access::Ro, Pdo::No);
    od.add(0x607D, 1, vec![0; 4], Access::Rw, Pdo::No);
    od.add(0x607D, 2, vec![0; 4], Access::Rw, Pdo::No);
    od.add(0x6081, 0, c(10.0), Access::Rw, Pdo::No);
    od.add(0x6083, 0, c(100.0), Access::Rw, Pdo::No);
    od.add(0x6084, 0, c(100.0), Access::Rw, Pdo::No);
    od.add(0x6085, 0, c(500.0), Access::Rw, Pdo::No);
    // CSP limits: max profile velocity, max acceleration.
    od.add(0x607F, 0, c(1000.0), Access::Rw, Pdo::No);
    od.add(0x60C5, 0, c(20_000.0), Access::Rw, Pdo::No);
    let s = cfg.scaling;
    od.add(0x608F, 0, vec![2], Access::Ro, Pdo::No);
    od.add(
        0x608F,
        1,
        s.encoder_increments.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(
        0x608F,
        2,
        s.motor_revolutions.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    // 0x6092:01 feed in µm of travel (this twin's unit), :02 shaft revolutions.
    od.add(0x6092, 0, vec![2], Access::Ro, Pdo::No);
    let feed_um = (s.feed_mm * 1000.0).round().clamp(0.0, u32::MAX as f64) as u32;
    od.add(
        0x6092,
        1,
        feed_um.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(
        0x6092,
        2,
        s.shaft_revolutions.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(0x6098, 0, vec![19], Access::Rw, Pdo::No);
    od.add(0x6099, 0, vec![2], Access::Ro, Pdo::No);
    od.add(0x6099, 1, c(5.0), Access::Rw, Pdo::No);
    od.add(0x6099, 2, c(0.5), Access::Rw, Pdo::No);
    od.add(0x609A, 0, c(50.0), Access::Rw, Pdo::No);
    // Supported drive modes: profile position (bit 0), homing (bit 5), cyclic synchronous
    // position (bit 7).
    od.add(
        0x6502,
        0,
        0xA1u32.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od
}
