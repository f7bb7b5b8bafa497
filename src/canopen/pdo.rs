//! PDOs and SYNC (CiA 301 §7.2.2, §7.2.5) for the follower drive.
//!
//! - The mapping the master writes by SDO in pre-operational: RPDO1 = controlword (0x6040) +
//!   target position (0x607A), TPDO1 = statusword (0x6041) + position actual (0x6064), both
//!   synchronous (transmission type 1), with the standard sequence: disable the PDO (COB-ID
//!   bit 31), zero the mapping count, write the entries, set the count, enable the PDO.
//! - The RPDO1/TPDO1 codecs (little-endian, in mapping order).
//! - The SYNC producer: an empty SYNC frame on 0x080 every period.

use super::sdo::ObjAddr;
use super::{cob, frame};
use crate::can::CanFrame;
use canopen_rs::NodeId;
use std::time::{Duration, Instant};

/// COB-ID bit 31: the PDO does not exist / is not valid.
pub const COB_INVALID: u32 = 1 << 31;
/// Transmission type: synchronous, every SYNC.
pub const SYNCHRONOUS: u8 = 1;

/// One mapping entry: object, sub-index and length in bits, as 0x1600/0x1A00 hold it
/// (`index << 16 | sub << 8 | bits`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MapEntry {
    pub index: u16,
    pub sub: u8,
    pub bits: u8,
}

impl MapEntry {
    pub const fn new(index: u16, sub: u8, bits: u8) -> Self {
        MapEntry { index, sub, bits }
    }
    pub fn encode(self) -> u32 {
        (self.index as u32) << 16 | (self.sub as u32) << 8 | self.bits as u32
    }
    pub fn decode(v: u32) -> Self {
        MapEntry {
            index: (v >> 16) as u16,
            sub: (v >> 8) as u8,
            bits: v as u8,
        }
    }
}

/// RPDO1 content: controlword, target position (in cyclic synchronous position, the position
/// demand of every SYNC).
pub const RPDO1_MAP: [MapEntry; 2] = [MapEntry::new(0x6040, 0, 16), MapEntry::new(0x607A, 0, 32)];
/// TPDO1 content: statusword, position actual value.
pub const TPDO1_MAP: [MapEntry; 2] = [MapEntry::new(0x6041, 0, 16), MapEntry::new(0x6064, 0, 32)];

/// One SDO write of a configuration sequence.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SdoWrite {
    pub obj: ObjAddr,
    pub data: Vec<u8>,
    /// An abort "object/sub-index does not exist" is tolerated (an optional object).
    pub optional: bool,
}

impl SdoWrite {
    pub fn u8(index: u16, sub: u8, v: u8) -> Self {
        Self::bytes(index, sub, vec![v])
    }
    pub fn i8(index: u16, sub: u8, v: i8) -> Self {
        Self::bytes(index, sub, vec![v as u8])
    }
    pub fn u16(index: u16, sub: u8, v: u16) -> Self {
        Self::bytes(index, sub, v.to_le_bytes().to_vec())
    }
    pub fn u32(index: u16, sub: u8, v: u32) -> Self {
        Self::bytes(index, sub, v.to_le_bytes().to_vec())
    }
    pub fn i32(index: u16, sub: u8, v: i32) -> Self {
        Self::bytes(index, sub, v.to_le_bytes().to_vec())
    }
    pub fn bytes(index: u16, sub: u8, data: Vec<u8>) -> Self {
        SdoWrite {
            obj: ObjAddr::new(index, sub),
            data,
            optional: false,
        }
    }
    pub fn optional(mut self) -> Self {
        self.optional = true;
        self
    }
}

/// Receive (master → drive) or transmit (drive → master) PDO.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PdoKind {
    Rpdo,
    Tpdo,
}

/// The standard sequence writing PDO number `num` (1..=4) of `kind`: COB-ID with bit 31
/// (disable), transmission type, mapping count 0, entries, count, COB-ID without bit 31.
pub fn mapping_sequence(
    kind: PdoKind,
    num: u8,
    cob_id: u16,
    transmission: u8,
    entries: &[MapEntry],
) -> Vec<SdoWrite> {
    let n = num.saturating_sub(1) as u16;
    let (comm, map) = match kind {
        PdoKind::Rpdo => (0x1400 + n, 0x1600 + n),
        PdoKind::Tpdo => (0x1800 + n, 0x1A00 + n),
    };
    let mut seq = vec![
        SdoWrite::u32(comm, 1, COB_INVALID | cob_id as u32),
        SdoWrite::u8(comm, 2, transmission),
        SdoWrite::u8(map, 0, 0),
    ];
    for (i, e) in entries.iter().enumerate() {
        seq.push(SdoWrite::u32(map, i as u8 + 1, e.encode()));
    }
    seq.push(SdoWrite::u8(map, 0, entries.len() as u8));
    seq.push(SdoWrite::u32(comm, 1, cob_id as u32));
    seq
}

/// The follower's PDO configuration: RPDO1 and TPDO1 mapped as above, synchronous; PDOs 2–4
/// disabled so they do not load the bus (optional: a drive may not have them).
pub fn follower_pdo_sequence(node: NodeId) -> Vec<SdoWrite> {
    let id = node.raw() as u16;
    let mut seq = mapping_sequence(PdoKind::Rpdo, 1, cob::RPDO1 + id, SYNCHRONOUS, &RPDO1_MAP);
    seq.extend(mapping_sequence(
        PdoKind::Tpdo,
        1,
        cob::TPDO1 + id,
        SYNCHRONOUS,
        &TPDO1_MAP,
    ));
    for k in 1..4u16 {
        // Predefined connection set: RPDOk+1 on 0x300/0x400/0x500 + node, TPDO on 0x280...
        let rpdo = 0x200 + 0x100 * k + id;
        let tpdo = 0x180 + 0x100 * k + id;
        seq.push(SdoWrite::u32(0x1400 + k, 1, COB_INVALID | rpdo as u32).optional());
        seq.push(SdoWrite::u32(0x1800 + k, 1, COB_INVALID | tpdo as u32).optional());
    }
    seq
}

/// RPDO1 frame: controlword (2 bytes LE), target position (4 bytes LE).
pub fn rpdo1_frame(node: NodeId, controlword: u16, target: i32) -> CanFrame {
    let mut d = [0u8; 6];
    d[0..2].copy_from_slice(&controlword.to_le_bytes());
    d[2..6].copy_from_slice(&target.to_le_bytes());
    frame(cob::RPDO1 + node.raw() as u16, &d)
}

/// TPDO1 data: statusword and position actual; `None` if shorter than 6 bytes.
pub fn decode_tpdo1(data: &[u8]) -> Option<(u16, i32)> {
    if data.len() < 6 {
        return None;
    }
    Some((
        u16::from_le_bytes([data[0], data[1]]),
        i32::from_le_bytes([data[2], data[3], data[4], data[5]]),
    ))
}

/// The SYNC producer: due every `period` from its start; missed periods are skipped, not
/// bunched (a late wake-up sends one SYNC and schedules the next from the grid).
///
/// While the master says the bus is quiet ([`set_quiet`](Self::set_quiet)) the SYNCs come
/// every `quiet_period` instead (a multiple of `period`, on the same grid); the first one
/// after the quiet ends is due one `period` after the last at the soonest.
#[derive(Debug)]
pub struct SyncProducer {
    period: Duration,
    quiet_period: Duration,
    quiet: bool,
    next: Option<Instant>,
    /// When the last SYNC was due.
    last: Option<Instant>,
    count: u64,
    /// SYNCs fall on `grid + n·period` when set (see [`align_to`](Self::align_to)).
    grid: Option<Instant>,
}

impl SyncProducer {
    pub fn new(period: Duration) -> Self {
        Self::with_quiet_period(period, period)
    }

    /// A producer that slows to `quiet_period` while quiet (`period` when shorter).
    pub fn with_quiet_period(period: Duration, quiet_period: Duration) -> Self {
        SyncProducer {
            period,
            quiet_period: quiet_period.max(period),
            quiet: false,
            next: None,
            last: None,
            count: 0,
            grid: None,
        }
    }

    /// Put the SYNCs on the grid `origin + n·period`, from the next start on. A loop that
    /// wakes on the same grid (the acquisition's pacer) then shares its wake-ups with the SYNC.
    pub fn align_to(&mut self, origin: Instant) {
        self.grid = Some(origin);
    }

    /// The first point at or after `t` of the grid of `period` (or `t` when not aligned).
    fn place(&self, t: Instant, period: Duration) -> Instant {
        match self.grid {
            Some(origin) => crate::util::pace::grid_point_at_or_after(origin, t, period),
            None => t,
        }
    }

    /// Start producing: the first SYNC is due at `now`, or at the first grid point from
    /// `now` on when aligned.
    pub fn start(&mut self, now: Instant) {
        if self.next.is_none() {
            self.next = Some(self.place(now, self.period));
        }
    }

    pub fn stop(&mut self) {
        self.next = None;
    }

    pub fn is_running(&self) -> bool {
        self.next.is_some()
    }

    /// Whether the SYNCs come at the quiet period now.
    pub fn is_quiet(&self) -> bool {
        self.quiet && self.quiet_period > self.period
    }

    /// The bus is quiet (nothing under way that needs the drive's status at every period) or
    /// no longer. Ending the quiet brings the next SYNC forward to one `period` after the last
    /// (on the grid when aligned), or to `now` if that has passed.
    pub fn set_quiet(&mut self, quiet: bool, now: Instant) {
        if quiet == self.quiet {
            return;
        }
        self.quiet = quiet;
        if !quiet && let Some(next) = self.next {
            let soonest = self.last.map_or(now, |l| (l + self.period).max(now));
            let at = self.place(soonest, self.period);
            if at < next {
                self.next = Some(at);
            }
        }
    }

    /// SYNC frames sent so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn poll_timeout(&self) -> Option<Instant> {
        self.next
    }

    /// Whether a SYNC is due at `now`; if so it is counted and the next one scheduled. The
    /// caller sends [`sync_frame`] (after any synchronous RPDO).
    pub fn handle_timeout(&mut self, now: Instant) -> bool {
        let Some(due) = self.next else {
            return false;
        };
        if now < due {
            return false;
        }
        let period = if self.is_quiet() {
            self.quiet_period
        } else {
            self.period
        };
        let next = match self.grid {
            // On the grid of the period in force, at least one period from now on.
            Some(_) => self.place(
                (due + self.period).max(now + Duration::from_nanos(1)),
                period,
            ),
            None => {
                let mut next = due + period;
                if next <= now {
                    let behind = now.duration_since(due).as_nanos() / period.as_nanos().max(1);
                    next = due + period * (behind as u32 + 1);
                }
                next
            }
        };
        self.next = Some(next);
        self.last = Some(due);
        self.count += 1;
        true
    }
}

/// The SYNC frame: COB-ID 0x080, no data (no counter).
pub fn sync_frame() -> CanFrame {
    frame(cob::SYNC, &[])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mapping_entries_encode() {
        assert_eq!(MapEntry::new(0x6040, 0, 16).encode(), 0x6040_0010);
        assert_eq!(MapEntry::new(0x607A, 0, 32).encode(), 0x607A_0020);
        assert_eq!(MapEntry::decode(0x6064_0020), MapEntry::new(0x6064, 0, 32));
    }

    /// The sequence, object by object and byte by byte, for node 1.
    #[test]
    fn follower_sequence_is_the_standard_one() {
        let seq = follower_pdo_sequence(NodeId::new(1).unwrap());
        let show: Vec<String> = seq
            .iter()
            .map(|w| {
                let hex: String = w.data.iter().map(|b| format!("{b:02X}")).collect();
                format!("{}={hex}{}", w.obj, if w.optional { "?" } else { "" })
            })
            .collect();
        assert_eq!(
            show,
            vec![
                "0x1400:01=01020080", // RPDO1 COB-ID 0x201 with bit 31: disabled
                "0x1400:02=01",       // synchronous
                "0x1600:00=00",       // mapping count 0
                "0x1600:01=10004060", // 0x6040 sub 0, 16 bits
                "0x1600:02=20007A60", // 0x607A sub 0, 32 bits
                "0x1600:00=02",
                "0x1400:01=01020000", // enabled
                "0x1800:01=81010080", // TPDO1 COB-ID 0x181, disabled
                "0x1800:02=01",
                "0x1A00:00=00",
                "0x1A00:01=10004160",
                "0x1A00:02=20006460",
                "0x1A00:00=02",
                "0x1800:01=81010000",
                "0x1401:01=01030080?",
                "0x1801:01=81020080?",
                "0x1402:01=01040080?",
                "0x1802:01=81030080?",
                "0x1403:01=01050080?",
                "0x1803:01=81040080?",
            ]
        );
    }

    #[test]
    fn pdo_codecs() {
        let f = rpdo1_frame(NodeId::new(3).unwrap(), 0x001F, -2);
        assert_eq!(format!("{f:?}"), "203#1F00FEFFFFFF");
        assert_eq!(
            decode_tpdo1(&[0x37, 0x16, 0x00, 0x00, 0x01, 0x00]),
            Some((0x1637, 0x0001_0000))
        );
        assert_eq!(decode_tpdo1(&[0x37, 0x16]), None);
        assert_eq!(format!("{:?}", sync_frame()), "080#");
    }

    #[test]
    fn sync_producer_keeps_its_grid() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let mut s = SyncProducer::new(Duration::from_millis(10));
        assert!(!s.handle_timeout(t0));
        s.start(t0);
        assert!(s.handle_timeout(t0));
        assert_eq!(s.poll_timeout(), Some(ms(10)));
        assert!(!s.handle_timeout(ms(9)));
        assert!(s.handle_timeout(ms(12)));
        assert_eq!(s.poll_timeout(), Some(ms(20)));
        // A late wake-up: one SYNC, next on the grid.
        assert!(s.handle_timeout(ms(47)));
        assert_eq!(s.poll_timeout(), Some(ms(50)));
        assert_eq!(s.count(), 3);
        s.stop();
        assert_eq!(s.poll_timeout(), None);
    }

    #[test]
    fn a_quiet_sync_producer_slows_on_its_grid_and_speeds_up_at_once() {
        let origin = crate::util::clock::now();
        let ms = |n: u64| origin + Duration::from_millis(n);
        let mut s =
            SyncProducer::with_quiet_period(Duration::from_millis(10), Duration::from_millis(100));
        s.align_to(origin);
        s.start(ms(0));
        assert!(s.handle_timeout(ms(0)));
        assert_eq!(s.poll_timeout(), Some(ms(10)));
        // Quiet: after the SYNC due now, the next one on the 100 ms grid.
        s.set_quiet(true, ms(5));
        assert!(s.is_quiet());
        assert!(s.handle_timeout(ms(10)));
        assert_eq!(s.poll_timeout(), Some(ms(100)));
        assert!(s.handle_timeout(ms(100)));
        assert_eq!(s.poll_timeout(), Some(ms(200)));
        // A command at 123 ms: the next SYNC on the 10 ms grid, not at 200 ms.
        s.set_quiet(false, ms(123));
        assert!(!s.is_quiet());
        assert_eq!(s.poll_timeout(), Some(ms(130)));
        // Ending the quiet right after a SYNC keeps a full period from it.
        s.set_quiet(true, ms(130));
        assert!(s.handle_timeout(ms(130)));
        assert_eq!(s.poll_timeout(), Some(ms(200)));
        s.set_quiet(false, ms(131));
        assert_eq!(s.poll_timeout(), Some(ms(140)));
        assert_eq!(s.count(), 4);
        // Not aligned: the quiet period counted from the SYNC.
        let mut u =
            SyncProducer::with_quiet_period(Duration::from_millis(10), Duration::from_millis(50));
        u.start(ms(3));
        u.set_quiet(true, ms(3));
        assert!(u.handle_timeout(ms(3)));
        assert_eq!(u.poll_timeout(), Some(ms(53)));
        u.set_quiet(false, ms(20));
        assert_eq!(u.poll_timeout(), Some(ms(20)));
        // One rate when the quiet period is not longer.
        let mut one = SyncProducer::new(Duration::from_millis(10));
        one.set_quiet(true, ms(0));
        assert!(!one.is_quiet());
    }

    #[test]
    fn an_aligned_sync_producer_starts_on_the_shared_grid() {
        let origin = crate::util::clock::now();
        let us = |n: u64| origin + Duration::from_micros(n);
        let mut s = SyncProducer::new(Duration::from_millis(10));
        s.align_to(origin);
        // Started 3.2 ms past a grid point: the first SYNC waits for the next one.
        s.start(us(23_200));
        assert_eq!(s.poll_timeout(), Some(us(30_000)));
        assert!(s.handle_timeout(us(30_050)));
        assert_eq!(s.poll_timeout(), Some(us(40_000)));
        // On a grid point: at once. Restarted after a stop: back on the grid.
        s.stop();
        s.start(us(60_000));
        assert_eq!(s.poll_timeout(), Some(us(60_000)));
        s.stop();
        s.start(us(60_001));
        assert_eq!(s.poll_timeout(), Some(us(70_000)));
        // Every SYNC is then a tick of a 2 ms pacer on the same origin.
        assert_eq!(
            crate::util::pace::grid_point_at_or_after(origin, us(60_001), Duration::from_millis(2)),
            us(62_000)
        );
    }
}
