//! The twin drive on a virtual clock, driven by literal frames (SDO, NMT, PDO, SYNC), and its
//! kinematics.

use super::*;
use crate::canopen::pdo::TPDO1_MAP;

fn parse(s: &str) -> CanFrame {
    let (id, data) = s.split_once('#').unwrap();
    let bytes: Vec<u8> = (0..data.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&data[i..i + 2], 16).unwrap())
        .collect();
    CanFrame::new(u16::from_str_radix(id, 16).unwrap(), &bytes).unwrap()
}

fn drive(t0: Instant) -> TwinDrive {
    TwinDrive::new(TwinDriveConfig::default(), Box::new(|_| {}), t0).unwrap()
}

fn out(d: &mut TwinDrive) -> Vec<String> {
    std::iter::from_fn(|| d.poll_transmit())
        .map(|f| format!("{f:?}"))
        .collect()
}

/// Send a request, return the answer.
fn ask(d: &mut TwinDrive, req: &str, now: Instant) -> String {
    d.handle_frame(&parse(req), now);
    let o = out(d);
    assert_eq!(o.len(), 1, "{req} → {o:?}");
    o[0].clone()
}

#[test]
fn boot_up_then_heartbeat_at_the_written_period() {
    let t0 = crate::util::clock::now();
    let ms = |n: u64| t0 + Duration::from_millis(n);
    let mut d = drive(t0);
    assert_eq!(out(&mut d), vec!["701#00"]);
    assert_eq!(d.poll_timeout(), None);
    // 0x1017 = 50 ms.
    assert_eq!(
        ask(&mut d, "601#2B17100032000000", t0),
        "581#6017100000000000"
    );
    assert_eq!(d.poll_timeout(), Some(ms(50)));
    d.handle_timeout(ms(50));
    assert_eq!(out(&mut d), vec!["701#7F"]);
    d.handle_frame(&parse("000#0101"), ms(60));
    d.handle_timeout(ms(100));
    // The default TPDO1 (statusword, event-driven) goes out on entering operational.
    assert_eq!(out(&mut d), vec!["181#5006", "701#05"]);
    d.set_heartbeat(false, ms(110));
    d.handle_timeout(ms(400));
    assert!(out(&mut d).is_empty());
    d.set_heartbeat(true, ms(400));
    d.handle_timeout(ms(450));
    assert_eq!(out(&mut d), vec!["701#05"]);
    // NMT to another node is ignored; broadcast stop is not.
    d.handle_frame(&parse("000#0202"), ms(460));
    d.handle_frame(&parse("000#0200"), ms(470));
    d.handle_timeout(ms(500));
    assert_eq!(out(&mut d), vec!["701#04"]);
    // Reset communication: boot-up, 0x1017 back to its default (no heartbeat).
    d.handle_frame(&parse("000#8201"), ms(510));
    assert_eq!(out(&mut d), vec!["701#00"]);
    assert_eq!(d.poll_timeout(), None);
}

/// The server's answers to python-canopen's requests equal python-canopen's own server.
#[test]
fn sdo_server_matches_python_canopen() {
    let t0 = crate::util::clock::now();
    let mut d = drive(t0);
    out(&mut d);
    assert_eq!(
        ask(&mut d, "601#2B4060000F000000", t0),
        "581#6040600000000000"
    );
    let trace = [
        ("601#2100200028000000", "581#6000200000000000"),
        ("601#0030313233343536", "581#2000000000000000"),
        ("601#103738393A3B3C3D", "581#3000000000000000"),
        ("601#003E3F4041424344", "581#2000000000000000"),
        ("601#1045464748494A4B", "581#3000000000000000"),
        ("601#004C4D4E4F505152", "581#2000000000000000"),
        ("601#1553545556570000", "581#3000000000000000"),
    ];
    for (req, resp) in trace {
        assert_eq!(ask(&mut d, req, t0), resp, "{req}");
    }
    // Read the 40 bytes back: segmented upload, 0x41 with the size, then 6 segments.
    assert_eq!(
        ask(&mut d, "601#4000200000000000", t0),
        "581#4100200028000000"
    );
    let segs = [
        ("601#6000000000000000", "581#0030313233343536"),
        ("601#7000000000000000", "581#103738393A3B3C3D"),
        ("601#6000000000000000", "581#003E3F4041424344"),
        ("601#7000000000000000", "581#1045464748494A4B"),
        ("601#6000000000000000", "581#004C4D4E4F505152"),
        ("601#7000000000000000", "581#1553545556570000"),
    ];
    for (req, resp) in segs {
        assert_eq!(ask(&mut d, req, t0), resp, "{req}");
    }
    // Expedited upload of the device type: 0x43, 4 bytes.
    assert_eq!(
        ask(&mut d, "601#4000100000000000", t0),
        "581#4300100092010200"
    );
    // A 1-byte object: 0x4F.
    assert_eq!(
        ask(&mut d, "601#4060600000000000", t0),
        "581#4F60600000000000"
    );
}

#[test]
fn sdo_server_aborts() {
    let t0 = crate::util::clock::now();
    let mut d = drive(t0);
    out(&mut d);
    // No object; no sub-index; read-only; too long; too short; bad toggle.
    assert_eq!(
        ask(&mut d, "601#4000300000000000", t0),
        "581#8000300000000206"
    );
    assert_eq!(
        ask(&mut d, "601#4000100100000000", t0),
        "581#8000100111000906"
    );
    assert_eq!(
        ask(&mut d, "601#2341600000000000", t0),
        "581#8041600002000106"
    );
    assert_eq!(
        ask(&mut d, "601#2340600000000000", t0),
        "581#8040600012000706"
    );
    assert_eq!(
        ask(&mut d, "601#2F7A600001000000", t0),
        "581#807A600013000706"
    );
    ask(&mut d, "601#2100200010000000", t0);
    assert_eq!(
        ask(&mut d, "601#1030313233343536", t0),
        "581#8000200000000305"
    );
    // Modes other than 0, 1, 6, 8 are refused.
    assert_eq!(
        ask(&mut d, "601#2F60600003000000", t0),
        "581#8060600030000906"
    );
    // Refusal injection names the object and code.
    d.refuse_sdo(Some(SdoRefusal {
        index: Some(0x6081),
        code: AbortCode::DEVICE_STATE,
    }));
    assert_eq!(
        ask(&mut d, "601#2381600000100000", t0),
        "581#8081600022000008"
    );
    assert_eq!(
        ask(&mut d, "601#4064600000000000", t0),
        "581#4364600000000000"
    );
    d.refuse_sdo(None);
    // Slow replies.
    d.set_sdo_delay(Duration::from_millis(300));
    d.handle_frame(&parse("601#4064600000000000"), t0);
    assert!(out(&mut d).is_empty());
    assert_eq!(d.poll_timeout(), Some(t0 + Duration::from_millis(300)));
    d.handle_timeout(t0 + Duration::from_millis(300));
    assert_eq!(out(&mut d), vec!["581#4364600000000000"]);
}

#[test]
fn pdo_mapping_rules_and_honoured_mapping() {
    let t0 = crate::util::clock::now();
    let mut d = drive(t0);
    out(&mut d);
    // Mapping while the PDO is valid: refused (device state).
    assert_eq!(
        ask(&mut d, "601#2F001A0000000000", t0),
        "581#80001A0022000008"
    );
    // Disable TPDO1, count 0.
    assert_eq!(
        ask(&mut d, "601#2300180181010080", t0),
        "581#6000180100000000"
    );
    assert_eq!(
        ask(&mut d, "601#2F001A0000000000", t0),
        "581#60001A0000000000"
    );
    // Entry writes with count 0 are fine; a receive-only object cannot go into a TPDO.
    ask(&mut d, "601#23001A0110004060", t0);
    assert_eq!(
        ask(&mut d, "601#2F001A0001000000", t0),
        "581#80001A0041000406"
    );
    // Nor a wrong length.
    ask(&mut d, "601#23001A0120004160", t0);
    assert_eq!(
        ask(&mut d, "601#2F001A0001000000", t0),
        "581#80001A0041000406"
    );
    // More than 64 bits.
    for (k, v) in [(1, "10004160"), (2, "20006460"), (3, "20006C60")] {
        ask(&mut d, &format!("601#23001A0{k}{v}"), t0);
    }
    assert_eq!(
        ask(&mut d, "601#2F001A0003000000", t0),
        "581#80001A0042000406"
    );
    // Entries with a count set: refused.
    ask(&mut d, "601#23001A0308006160", t0);
    assert_eq!(
        ask(&mut d, "601#2F001A0003000000", t0),
        "581#60001A0000000000"
    );
    assert_eq!(
        ask(&mut d, "601#23001A0110004160", t0),
        "581#80001A0122000008"
    );
    // Enable: statusword + position + mode display (7 bytes), synchronous.
    ask(&mut d, "601#2F00180201000000", t0);
    ask(&mut d, "601#2300180181010000", t0);
    // Changing the COB-ID of a valid PDO is refused.
    assert_eq!(
        ask(&mut d, "601#2300180182010000", t0),
        "581#8000180130000906"
    );
    assert_eq!(
        d.status().tpdo1_map,
        vec![TPDO1_MAP[0], TPDO1_MAP[1], MapEntry::new(0x6061, 0, 8)]
    );
    // No PDO before operational.
    d.handle_frame(&parse("080#"), t0);
    assert!(out(&mut d).is_empty());
    d.handle_frame(&parse("000#0100"), t0);
    d.handle_frame(&parse("080#"), t0);
    // 0x0650: switch on disabled 0x40, voltage 0x10, remote 0x200, target reached 0x400;
    // position 0 (4 bytes), mode 0 (1 byte).
    assert_eq!(out(&mut d), vec!["181#50060000000000"]);
}

#[test]
fn controlword_drives_the_fsa_and_statusword() {
    let t0 = crate::util::clock::now();
    let mut d = drive(t0);
    out(&mut d);
    let sw = |d: &mut TwinDrive, cw: u16| {
        let v = cw.to_le_bytes();
        ask(d, &format!("601#2B406000{:02X}{:02X}0000", v[0], v[1]), t0);
        d.status().statusword
    };
    assert_eq!(sw(&mut d, 0x06), 0x0631);
    assert_eq!(sw(&mut d, 0x07), 0x0633);
    assert_eq!(sw(&mut d, 0x0F), 0x0637);
    assert_eq!(d.status().state, PowerState::OperationEnabled);
    assert_eq!(sw(&mut d, 0x07), 0x0633);
    assert_eq!(sw(&mut d, 0x0F), 0x0637);
    // Quick stop at standstill: quick stop active ends at once in switch on disabled
    // (0x605A = 2).
    assert_eq!(sw(&mut d, 0x02), 0x0650);
    assert_eq!(sw(&mut d, 0x06), 0x0631);
    assert_eq!(sw(&mut d, 0x00), 0x0650);
}

#[test]
fn fault_injection_emcy_and_reset() {
    let t0 = crate::util::clock::now();
    let mut d = drive(t0);
    out(&mut d);
    d.inject_fault(0x8611, [0xDE, 0xAD, 0, 0, 1], t0);
    // Code 0x8611 LE, register generic + device profile, manufacturer bytes.
    assert_eq!(out(&mut d), vec!["081#118621DEAD000001"]);
    let s = d.status();
    assert_eq!(s.state, PowerState::Fault);
    assert_eq!(s.fault_code, 0x8611);
    assert_eq!(
        ask(&mut d, "601#403F600000000000", t0),
        "581#4B3F600011860000"
    );
    assert_eq!(
        ask(&mut d, "601#4001100000000000", t0),
        "581#4F01100021000000"
    );
    // Enable does nothing in fault; the rising edge of bit 7 resets, with an EMCY reset.
    ask(&mut d, "601#2B4060000F000000", t0);
    assert_eq!(d.status().state, PowerState::Fault);
    d.handle_frame(&parse("601#2B40600080000000"), t0);
    assert_eq!(
        out(&mut d),
        vec!["081#0000000000000000", "581#6040600000000000"]
    );
    assert_eq!(d.status().state, PowerState::SwitchOnDisabled);
    assert_eq!(d.status().fault_code, 0);
}

/// A 10 mm move at 10 mm/s with 100 mm/s² ramps: 0.1 s up, 0.9 s cruise, 0.1 s down.
#[test]
fn trapezoidal_profile() {
    let mut m = Mover {
        pos: 0.0,
        vel: 0.0,
        goal: Goal::To {
            target: 10.0,
            v: 10.0,
            a: 100.0,
            d: 100.0,
        },
    };
    let dt = 1e-4;
    let mut t = 0.0;
    let mut at = |m: &mut Mover, until: f64| {
        while t < until - 1e-12 {
            if m.step(dt) {
                return true;
            }
            t += dt;
        }
        false
    };
    assert!(!at(&mut m, 0.1));
    // End of the ramp: v = 10 mm/s, s = ½·a·t² = 0.5 mm.
    assert!((m.vel - 10.0).abs() < 1e-6, "{m:?}");
    assert!((m.pos - 0.5).abs() < 1e-3, "{m:?}");
    assert!(!at(&mut m, 0.55));
    assert!((m.pos - 5.0).abs() < 1e-3);
    assert!(!at(&mut m, 1.0));
    assert!((m.pos - 9.5).abs() < 2e-3, "{m:?}");
    // Braking, then arrival at 1.1 s.
    assert!(at(&mut m, 1.2));
    assert!((t - 1.1).abs() < 2e-3, "{t}");
    assert_eq!(m.pos, 10.0);
    assert_eq!(m.vel, 0.0);
    assert!(!m.moving());
    // A short move is a triangle: peak √(a·s) for equal ramps.
    let mut m = Mover {
        pos: 0.0,
        vel: 0.0,
        goal: Goal::To {
            target: 0.25,
            v: 10.0,
            a: 100.0,
            d: 100.0,
        },
    };
    let mut peak: f64 = 0.0;
    let mut n = 0;
    while !m.step(dt) {
        peak = peak.max(m.vel);
        n += 1;
    }
    assert!((peak - 5.0).abs() < 0.05, "{peak}");
    assert!((n as f64 * dt - 0.1).abs() < 2e-3);
    // Braking from speed with a stop goal: v²/(2d) = 0.5 mm.
    let mut m = Mover {
        pos: 0.0,
        vel: 10.0,
        goal: Goal::Stop { d: 100.0 },
    };
    while !m.step(dt) {}
    assert!((m.pos - 0.5).abs() < 1e-3, "{m:?}");
}

#[test]
fn position_reaches_the_plant_callback() {
    let t0 = crate::util::clock::now();
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let s = seen.clone();
    let mut d = TwinDrive::new(
        TwinDriveConfig {
            start_mm: 1.5,
            ..Default::default()
        },
        Box::new(move |mm| s.lock().unwrap().push(mm)),
        t0,
    )
    .unwrap();
    assert_eq!(*seen.lock().unwrap(), vec![1.5]);
    out(&mut d);
    // Enable, homing mode, start homing: the stage drives to the switch at 0.
    for cw in ["06", "07", "0F"] {
        ask(&mut d, &format!("601#2B406000{cw}000000"), t0);
    }
    ask(&mut d, "601#2F60600006000000", t0);
    ask(&mut d, "601#2B4060001F000000", t0);
    let mut t = t0;
    while d.poll_timeout().is_some() && t < t0 + Duration::from_secs(10) {
        t = d.poll_timeout().unwrap();
        d.handle_timeout(t);
    }
    let v = seen.lock().unwrap().clone();
    assert_eq!(*v.last().unwrap(), 0.0);
    assert!(
        v.len() > 100 && v.windows(2).all(|w| w[1] <= w[0]),
        "monotonic"
    );
    let s = d.status();
    assert!(s.homed && !s.moving);
    assert_eq!(s.position_mm, 0.0);
    // Homing attained + target reached in homing mode: 0x1637.
    assert_eq!(s.statusword, 0x1637);
}

/// A drive with RPDO1 = controlword + target position (synchronous), 0x607F = 20 mm/s,
/// 0x60C5 = 200 mm/s², enabled in mode 8 and operational, its output drained.
fn csp_drive(t0: Instant) -> TwinDrive {
    let mut d = drive(t0);
    out(&mut d);
    for req in [
        "601#2300140101020080",
        "601#2F00140201000000",
        "601#2F00160000000000",
        "601#2300160110004060",
        "601#2300160220007A60",
        "601#2F00160002000000",
        "601#2300140101020000",
        // 0x607F = 20 mm/s = 524 288 inc/s; 0x60C5 = 200 mm/s² = 5 242 880 inc/s².
        "601#237F600000000800",
        "601#23C5600000005000",
    ] {
        assert!(ask(&mut d, req, t0).starts_with("581#60"), "{req}");
    }
    for cw in ["06", "07", "0F"] {
        ask(&mut d, &format!("601#2B406000{cw}000000"), t0);
    }
    assert_eq!(
        ask(&mut d, "601#2F60600008000000", t0),
        "581#6060600000000000"
    );
    assert_eq!(
        ask(&mut d, "601#4061600000000000", t0),
        "581#4F61600008000000"
    );
    // Operation enabled 0x0237 with bit 12 (target used), not bit 10.
    assert_eq!(d.status().statusword, 0x1237);
    d.handle_frame(&parse("000#0100"), t0);
    out(&mut d);
    d
}

/// RPDO1 with controlword 0x000F and `mm` as the target position, then SYNC, at `t`.
fn csp_demand(d: &mut TwinDrive, mm: f64, t: Instant) {
    let c = (mm * Scaling::default().counts_per_mm()).round() as i32;
    let b = c.to_le_bytes();
    let rpdo = format!("201#0F00{:02X}{:02X}{:02X}{:02X}", b[0], b[1], b[2], b[3]);
    d.handle_frame(&parse(&rpdo), t);
    d.handle_frame(&parse("080#"), t);
    out(d);
}

/// A demand 5 ms late while the motion is steady: the internal demand goes on at the same
/// velocity meanwhile (no stop and go). At the end of a move (the velocity changing by
/// more than a quarter) a late demand finds it holding: the stage stops on the last demand
/// without going past it by more than its servo's overshoot.
#[test]
fn csp_late_demand_while_steady_and_at_the_end() {
    let t0 = crate::util::clock::now();
    let ms = |n: u64| t0 + Duration::from_millis(n);
    let mut d = csp_drive(t0);
    // Positions as the drive has them, in whole increments.
    let cpm = Scaling::default().counts_per_mm();
    let q = |mm: f64| (mm * cpm).round() / cpm;
    let at = |d: &TwinDrive| d.status().physical_mm;
    // 10 mm/s: 0.1 mm per 10 ms SYNC.
    for k in 0..30u64 {
        csp_demand(&mut d, 0.1 * k as f64, ms(10 * k));
        d.handle_timeout(ms(10 * k + 5));
    }
    // One cycle behind: at 295 ms the stage is at 2.85 mm (demand 2.9 reached at 300).
    assert!((at(&d) - 2.85).abs() < 1e-4, "{:?}", d.status());
    // The next demand comes at 305 instead of 300: at 303 the stage went on to 2.93.
    d.handle_timeout(ms(303));
    assert!((at(&d) - 2.93).abs() < 1e-4, "{:?}", d.status());
    csp_demand(&mut d, 3.0, ms(305));
    // Braking at 100 mm/s² (1 mm/s less each cycle) to rest at 3.45 mm; the demand after
    // the last step comes 15 ms late.
    let mut x = 3.0;
    for k in 1..=9u64 {
        x += 0.01 * (10 - k) as f64;
        csp_demand(&mut d, x, ms(305 + 10 * k));
    }
    d.handle_timeout(ms(410));
    let mut max = at(&d);
    d.handle_timeout(ms(420));
    max = max.max(at(&d));
    assert_eq!(at(&d), q(3.45), "{:?}", d.status());
    for k in 0..20u64 {
        csp_demand(&mut d, 3.45, ms(410 + 10 * k));
        d.handle_timeout(ms(415 + 10 * k));
        max = max.max(at(&d));
    }
    // Past it only by the servo's own overshoot (a few µm), not by going on for the late
    // cycle (1 mm/s × 15 ms = 15 µm).
    assert!(max - q(3.45) < 0.005, "{max}");
    assert!(at(&d) == q(3.45) && !d.status().moving, "{:?}", d.status());
}

/// Mode 8 on the wire: RPDO1 mapped to controlword + target position (synchronous), the
/// drive enabled, 0x6060 = 8. Each RPDO at SYNC is a new demand, no handshake: the stage
/// follows a 15 mm/s ramp one SYNC behind, within 0x607F (20 mm/s) and 0x60C5
/// (200 mm/s²), reports a following error (bit 13) while the start of the ramp is beyond
/// its acceleration, bit 12 while it uses the target, bit 10 never (reserved), and stops
/// exactly on a held demand; a jump is run at the velocity limit.
#[test]
fn csp_follows_demands_within_its_limits() {
    let t0 = crate::util::clock::now();
    let ms = |n: u64| t0 + Duration::from_millis(n);
    let mut d = csp_drive(t0);
    let cpm = Scaling::default().counts_per_mm();
    let mut samples: Vec<(f64, f64, u16)> = vec![];
    // RPDO + SYNC every 10 ms from `from` to `to` ms with the demand at each, sampling the
    // stage at every motion tick.
    let run = |d: &mut TwinDrive,
               samples: &mut Vec<(f64, f64, u16)>,
               from: u64,
               to: u64,
               demand: &dyn Fn(u64) -> f64| {
        for k in (from..to).step_by(10) {
            let c = (demand(k) * cpm).round() as i32;
            let b = c.to_le_bytes();
            let rpdo = format!("201#0F00{:02X}{:02X}{:02X}{:02X}", b[0], b[1], b[2], b[3]);
            d.handle_frame(&parse(&rpdo), ms(k));
            d.handle_frame(&parse("080#"), ms(k));
            out(d);
            let end = ms(k + 10);
            while let Some(n) = d.poll_timeout().filter(|n| *n < end) {
                d.handle_timeout(n);
                let s = d.status();
                samples.push(((n - t0).as_secs_f64(), s.physical_mm, s.statusword));
            }
            d.handle_timeout(end);
            let s = d.status();
            samples.push(((end - t0).as_secs_f64(), s.physical_mm, s.statusword));
        }
    };
    let ramp = |k: u64| 15.0 * k as f64 / 1000.0;
    run(&mut d, &mut samples, 0, 500, &ramp);
    // Caught up: one SYNC behind the ramp (the demand taken at k is reached at k + 10 ms).
    for &(t, x, sw) in samples.iter().filter(|s| s.0 >= 0.3) {
        assert!((x - 15.0 * (t - 0.01)).abs() < 1e-3, "{t}: {x}");
        assert_eq!(sw, 0x1237, "{t}");
    }
    let lagging = samples.iter().filter(|s| s.2 & 0x2000 != 0).count();
    assert!(lagging > 0, "following error while accelerating");
    assert!(samples.iter().all(|s| s.2 & 0x0400 == 0), "bit 10 reserved");
    // Hold at 7.5 mm (the last demand of the ramp is 7.35), then a 5 mm jump.
    run(&mut d, &mut samples, 500, 900, &|_| 7.5);
    assert_eq!(d.status().physical_mm, 7.5);
    assert_eq!(d.status().statusword, 0x1237);
    assert_eq!(d.status().demand_mm, Some(7.5));
    run(&mut d, &mut samples, 900, 1500, &|_| 12.5);
    assert_eq!(d.status().physical_mm, 12.5);
    assert_eq!(d.status().statusword, 0x1237);
    assert!(!d.status().moving);
    // The limits, from the sampled positions (2 ms apart or less).
    let v: Vec<(f64, f64)> = samples
        .windows(2)
        .filter(|w| w[1].0 > w[0].0)
        .map(|w| (w[1].0, (w[1].1 - w[0].1) / (w[1].0 - w[0].0)))
        .collect();
    let vmax = v.iter().map(|x| x.1.abs()).fold(0.0, f64::max);
    assert!(vmax <= 20.0 + 1e-6 && vmax > 19.9, "{vmax}");
    for w in v.windows(2) {
        let a = (w[1].1 - w[0].1) / (w[1].0 - w[0].0);
        assert!(
            a.abs() <= 200.0 * (1.0 + 1e-6) + 1e-6,
            "{a} mm/s² at {}",
            w[1].0
        );
    }
    // Halt: the target is ignored (bit 12 clear) and the stage stays.
    d.handle_frame(&parse("201#0F01000000FF"), ms(1500));
    d.handle_frame(&parse("080#"), ms(1500));
    d.handle_timeout(ms(1700));
    let s = d.status();
    assert_eq!(s.physical_mm, 12.5);
    assert_eq!(s.statusword & 0x1000, 0);
    assert_eq!(s.demand_mm, None);
}
