//! The master against the twin drive's machine, both on one virtual clock: frames are
//! delivered at once, time jumps from deadline to deadline.
//!
//! The rig and helpers are here; the tests by topic: `commands` (configure, NMT, power,
//! homing, profile position, stops, faults, SDO, heartbeat, the SYNC's pace) and
//! `following` (cyclic synchronous position).

use super::*;
use crate::sim::drive::{TwinDrive, TwinDriveConfig};
use std::sync::{Arc, Mutex};

mod commands;
mod following;

struct Rig {
    t: Instant,
    t0: Instant,
    m: Master,
    d: TwinDrive,
    events: Vec<(Duration, Event)>,
    log: Vec<String>,
    plant: Arc<Mutex<f64>>,
}

impl Rig {
    fn new(cfg: DriveConfig, twin: TwinDriveConfig) -> Rig {
        let t0 = crate::util::clock::now();
        let plant = Arc::new(Mutex::new(f64::NAN));
        let p = plant.clone();
        let d = TwinDrive::new(twin, Box::new(move |mm| *p.lock().unwrap() = mm), t0).unwrap();
        let mut r = Rig {
            t: t0,
            t0,
            m: Master::new(&cfg).unwrap(),
            d,
            events: vec![],
            log: vec![],
            plant,
        };
        r.pump();
        r
    }

    fn default() -> Rig {
        Rig::new(
            DriveConfig::default(),
            TwinDriveConfig {
                start_mm: 2.0,
                ..Default::default()
            },
        )
    }

    fn pump(&mut self) {
        for _ in 0..10_000 {
            let mut any = false;
            while let Some(f) = self.m.poll_transmit() {
                self.log.push(format!("{f:?}"));
                self.d.handle_frame(&f, self.t);
                any = true;
            }
            while let Some(f) = self.d.poll_transmit() {
                self.log.push(format!("{f:?}"));
                self.m.handle_frame(&f, self.t);
                any = true;
            }
            while let Some(e) = self.m.poll_event() {
                self.events.push((self.t - self.t0, e));
            }
            if !any {
                return;
            }
        }
        panic!("the machines keep talking");
    }

    /// Let `dur` of virtual time pass.
    fn advance(&mut self, dur: Duration) {
        let end = self.t + dur;
        for _ in 0..10_000_000 {
            self.pump();
            let next = [self.m.poll_timeout(), self.d.poll_timeout()]
                .into_iter()
                .flatten()
                .min();
            match next {
                Some(n) if n <= end => {
                    self.t = self.t.max(n);
                    self.m.handle_timeout(self.t);
                    self.d.handle_timeout(self.t);
                }
                _ => {
                    self.t = end;
                    self.pump();
                    return;
                }
            }
        }
        panic!("time does not advance");
    }

    fn completion(&self, id: OpId) -> Option<Result<Reply, DriveError>> {
        self.events.iter().find_map(|(_, e)| match e {
            Event::Completed { id: i, result } if *i == id => Some(result.clone()),
            _ => None,
        })
    }

    /// Submit and run until done (at most `limit` of virtual time).
    fn run(&mut self, cmd: Command, limit: Duration) -> Result<Reply, DriveError> {
        let id = self.m.submit(cmd, self.t);
        let end = self.t + limit;
        while self.t < end {
            self.advance(Duration::from_millis(5));
            if let Some(r) = self.completion(id) {
                return r;
            }
        }
        panic!("command {id} not done within {limit:?}");
    }

    fn ok(&mut self, cmd: Command) {
        let name = cmd.name();
        if let Err(e) = self.run(cmd, Duration::from_secs(60)) {
            panic!("{name}: {e}");
        }
    }

    fn ready(&mut self) {
        self.ok(Command::Configure);
        self.ok(Command::Start);
        self.ok(Command::Enable);
        self.ok(Command::Home);
    }

    fn frames_since(&self, start: usize, prefix: &str) -> Vec<String> {
        self.log[start..]
            .iter()
            .filter(|l| l.starts_with(prefix))
            .cloned()
            .collect()
    }

    /// The distinct successive controlwords of the RPDO1 frames since `start`.
    fn controlwords(&self, start: usize) -> Vec<u16> {
        let mut v: Vec<u16> = vec![];
        for l in self.frames_since(start, "201#") {
            let cw = u16::from_str_radix(&l[6..8], 16).unwrap() << 8
                | u16::from_str_radix(&l[4..6], 16).unwrap();
            if v.last() != Some(&cw) {
                v.push(cw);
            }
        }
        v
    }
}

fn hex_le(v: i32) -> String {
    v.to_le_bytes().iter().map(|b| format!("{b:02X}")).collect()
}

/// A config for following: 60 mm/s, 600 mm/s² (6 mm/s and 0.06 mm per SYNC² at 10 ms).
fn csp_config() -> DriveConfig {
    DriveConfig {
        profile: crate::canopen::ProfileConfig {
            velocity_mm_s: 60.0,
            accel_mm_s2: 600.0,
            decel_mm_s2: 600.0,
            ..Default::default()
        },
        ..Default::default()
    }
}

fn csp_rig() -> Rig {
    let mut r = Rig::new(
        csp_config(),
        TwinDriveConfig {
            start_mm: 2.0,
            ..Default::default()
        },
    );
    r.ready();
    r
}

/// The target positions (0x607A) of the RPDO1 frames since `start`, with their
/// controlwords.
fn rpdos(r: &Rig, start: usize) -> Vec<(u16, i32)> {
    r.frames_since(start, "201#")
        .iter()
        .map(|l| {
            let b: Vec<u8> = (4..l.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&l[i..i + 2], 16).unwrap())
                .collect();
            (
                u16::from_le_bytes([b[0], b[1]]),
                i32::from_le_bytes([b[2], b[3], b[4], b[5]]),
            )
        })
        .collect()
}

fn following_events(r: &Rig) -> Vec<Event> {
    r.events
        .iter()
        .filter(|(_, e)| matches!(e, Event::FollowingStarted | Event::FollowingEnded(_)))
        .map(|(_, e)| e.clone())
        .collect()
}
