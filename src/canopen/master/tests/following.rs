//! Following in cyclic synchronous position.

use super::*;
use crate::canopen::cia402::{MODE_CSP, MODE_HOMING, MODE_PROFILE_POSITION};
use crate::canopen::sdo::AbortCode;
use crate::sim::drive::SdoRefusal;

/// Following that starts after a quiet spell runs as it does from the full rate: the
/// ramp's first step is one SYNC period, not the 100 ms since the last quiet SYNC (which
/// the twin, like a drive, answered with a following error).
#[test]
fn following_after_a_quiet_spell_has_no_following_error() {
    let mut r = Rig::new(
        DriveConfig {
            quiet_sync_period: Duration::from_millis(100),
            ..csp_config()
        },
        TwinDriveConfig {
            start_mm: 2.0,
            ..Default::default()
        },
    );
    r.ready();
    r.advance(QUIET_AFTER * 2);
    assert!(r.m.status().sync_quiet);
    let t0 = r.t;
    while r.t - t0 < Duration::from_millis(800) {
        let target = 2.0 + 20.0 * (r.t - t0).as_secs_f64();
        r.m.follow_moving(target, Some(20.0), r.t, r.t)
            .unwrap_or_else(|e| panic!("{e}: {:?}", following_events(&r)));
        r.advance(Duration::from_millis(2));
    }
    assert_eq!(following_events(&r), vec![Event::FollowingStarted]);
}

/// The whole CSP sequence on the wire: the demand held at the actual position, 0x6060 = 8
/// by SDO, 0x6061 read back until it shows 8, then at every SYNC an RPDO1 with
/// controlword 0x000F and the ramped demand (closed form a·T²·k(k+1)/2 while
/// accelerating), no handshake; at rest the master's "target reached"; a move switches
/// back to profile position (0x6060 = 1) and runs its set-point handshake.
#[test]
fn csp_sequence_on_the_wire() {
    let mut r = csp_rig();
    let cpm = r.m.settings().counts_per_mm();
    assert_eq!(r.m.status().position_counts, Some(0));
    let start = r.log.len();
    r.m.follow(5.0, r.t, r.t).unwrap();
    // Mode switch: write 0x6060 = 8 (0x2F: expedited, 1 byte), read 0x6061, the drive
    // answers 8 (0x4F: expedited upload of 1 byte).
    let write = "601#2F60600008000000";
    let read = "601#4061600000000000";
    let shows8 = "581#4F61600008000000";
    while !r.log[start..].iter().any(|l| l == shows8) {
        r.advance(Duration::from_millis(1));
    }
    let at = |l: &str| r.log[start..].iter().position(|x| x == l).unwrap() + start;
    assert!(at(write) < at(read) && at(read) < at(shows8));
    // Up to the confirmation every RPDO holds the actual position (0) with no set-point
    // bits: 0x000F.
    let held = rpdos(&r, start);
    assert!(
        held.iter().all(|&(cw, t)| cw == 0x000F && t == 0),
        "{held:?}"
    );
    let from = at(shows8);
    r.advance(Duration::from_millis(60));
    let demands = rpdos(&r, from);
    assert!(demands.len() >= 5);
    let step = 600.0 * 0.01 * 0.01;
    for (k, &(cw, t)) in demands.iter().take(5).enumerate() {
        let k = (k + 1) as f64;
        let mm = step * k * (k + 1.0) / 2.0;
        assert_eq!(cw, 0x000F);
        assert_eq!(t, (mm * cpm).round() as i32, "SYNC {k}");
    }
    // The RPDO bytes themselves: COB-ID 0x201, controlword 0F 00, 0x607A LE.
    let first = r.frames_since(from, "201#")[0].clone();
    assert_eq!(
        first,
        format!("201#0F00{}", hex_le((step * cpm).round() as i32))
    );
    // Each RPDO still goes out right before its SYNC.
    let i = r.log.iter().rposition(|l| l.starts_with("201#")).unwrap();
    assert_eq!(r.log[i + 1], "080#");
    assert!(r.m.status().following && !r.m.status().target_reached);
    r.advance(Duration::from_secs(1));
    let st = r.m.status();
    assert_eq!(st.mode, Some(MODE_CSP));
    assert!(
        st.following && st.target_reached && !st.following_error,
        "{st:?}"
    );
    assert!((st.position_mm.unwrap() - 5.0).abs() < 1.0 / cpm, "{st:?}");
    // The drive's TPDO: operation enabled 0x0237 + bit 12 "target position used", bit 10
    // reserved (0) in CSP.
    let tpdo = r.log.iter().rev().find(|l| l.starts_with("181#")).unwrap();
    assert!(tpdo.starts_with("181#3712"), "{tpdo}");
    assert_eq!(r.d.status().mode, MODE_CSP);
    // A move leaves CSP: 0x6060 = 1, confirmed, then the set-point handshake.
    let start = r.log.len();
    r.ok(Command::MoveTo { target_mm: 2.0 });
    let sdo = r.frames_since(start, "601#");
    assert!(sdo.contains(&"601#2F60600001000000".to_string()), "{sdo:?}");
    assert!(r.log[start..].contains(&"581#4F61600001000000".to_string()));
    assert!(r.controlwords(start).ends_with(&[0x001F, 0x000F]));
    let st = r.m.status();
    assert_eq!(st.mode, Some(MODE_PROFILE_POSITION));
    assert!(!st.following && st.target_reached);
    assert!((st.position_mm.unwrap() - 2.0).abs() < 1.0 / cpm);
    assert_eq!(
        following_events(&r),
        vec![Event::FollowingStarted, Event::FollowingEnded(Ok(()))]
    );
}

/// Demands stay within the profile velocity and acceleration whatever the target does;
/// a moving target is followed closely; `StopFollowing` rests on the last target and
/// returns to profile position.
#[test]
fn csp_ramp_limits_and_tracking() {
    let mut r = csp_rig();
    let cpm = r.m.settings().counts_per_mm();
    let start = r.log.len();
    // A target at 40 mm/s for 0.5 s, updated every 2 ms, then a jump back to -20 mm.
    let t0 = r.t;
    let mut worst: f64 = 0.0;
    while r.t - t0 < Duration::from_millis(500) {
        let target = 40.0 * (r.t - t0).as_secs_f64();
        r.m.follow(target, r.t, r.t)
            .unwrap_or_else(|e| panic!("{e}: {:?}", following_events(&r)));
        r.advance(Duration::from_millis(2));
        if r.t - t0 > Duration::from_millis(250) {
            // Caught up: the stage within half a millimetre of the moving target.
            worst = worst.max((*r.plant.lock().unwrap() - target).abs());
        }
    }
    assert!(worst < 0.5, "{worst} mm behind");
    r.m.follow(-20.0, r.t, r.t).unwrap();
    r.advance(Duration::from_secs(2));
    let d: Vec<f64> = rpdos(&r, start)
        .iter()
        .map(|&(_, t)| t as f64 / cpm)
        .collect();
    let v: Vec<f64> = d.windows(2).map(|w| (w[1] - w[0]) / 0.01).collect();
    let q = 1.0 / cpm / 0.01; // one increment per SYNC, in mm/s
    assert!(v.iter().all(|x| x.abs() <= 60.0 + 2.0 * q), "{v:?}");
    assert!(
        v.windows(2)
            .all(|w| ((w[1] - w[0]) / 0.01).abs() <= 600.0 + 4.0 * q / 0.01),
        "acceleration"
    );
    assert!(v.iter().any(|x| x.abs() > 59.0), "cruised at the limit");
    let st = r.m.status();
    assert!(st.following && st.target_reached && !st.following_error);
    assert_eq!(st.position_counts, Some((-20.0 * cpm).round() as i32));
    // Stop following: back to profile position, at rest on the last target.
    r.ok(Command::StopFollowing);
    let st = r.m.status();
    assert!(
        !st.following && st.mode == Some(MODE_PROFILE_POSITION),
        "{st:?}"
    );
    assert_eq!(st.commanded_mm, Some((-20.0 * cpm).round() / cpm));
    assert_eq!(r.d.status().mode, MODE_PROFILE_POSITION);
    // A second stop is a no-op; a relative jog works from the last demand.
    r.ok(Command::StopFollowing);
    r.ok(Command::Jog { delta_mm: 1.0 });
    assert!((r.m.status().position_mm.unwrap() + 19.0).abs() < 1e-4);
}

/// Stop following while the target still moves: the demand is brought to rest on the
/// last target (overshooting within the limits), then profile position.
#[test]
fn stop_following_while_moving() {
    let mut r = csp_rig();
    let t0 = r.t;
    let mut last = 0.0;
    while r.t - t0 < Duration::from_millis(300) {
        last = 30.0 * (r.t - t0).as_secs_f64();
        r.m.follow(last, r.t, r.t).unwrap();
        r.advance(Duration::from_millis(2));
    }
    r.ok(Command::StopFollowing);
    let cpm = r.m.settings().counts_per_mm();
    let st = r.m.status();
    assert_eq!(st.position_counts, Some((last * cpm).round() as i32));
    assert_eq!(st.mode, Some(MODE_PROFILE_POSITION));
}

/// The drive cannot keep up (its own maximum acceleration 0x60C5 lowered below the
/// profile's): it reports bit 13, the master surfaces it, ends following and refuses follow
/// targets until the next command.
#[test]
fn csp_following_error_ends_following() {
    let mut r = csp_rig();
    // 0x60C5 = 20 mm/s² on the drive (524 288 increments/s²).
    r.ok(Command::SdoWrite(
        ObjAddr::new(0x60C5, 0),
        524_288u32.to_le_bytes().to_vec(),
    ));
    r.m.follow(10.0, r.t, r.t).unwrap();
    let t0 = r.t;
    while !r.m.status().following && r.t - t0 < Duration::from_secs(1) {
        r.advance(Duration::from_millis(1));
    }
    while r.m.status().following && r.t - t0 < Duration::from_secs(2) {
        r.advance(Duration::from_millis(1));
    }
    // Surfaced in the status with the TPDO that ended following.
    let st = r.m.status();
    assert!(st.following_error && !st.following, "{st:?}");
    assert_eq!(st.statusword.map(|w| w & 0x3400), Some(0x3000));
    assert!(
        r.log
            .iter()
            .any(|l| l.starts_with("181#37")
                && u16::from_str_radix(&l[6..8], 16).unwrap() & 0x20 != 0),
        "a TPDO with bit 13"
    );
    assert_eq!(
        following_events(&r),
        vec![
            Event::FollowingStarted,
            Event::FollowingEnded(Err(DriveError::FollowingError))
        ]
    );
    assert_eq!(r.m.follow(3.0, r.t, r.t), Err(DriveError::FollowDisarmed));
    // Limit back to 20 000 mm/s²; after another command following works again.
    r.ok(Command::SdoWrite(
        ObjAddr::new(0x60C5, 0),
        524_288_000u32.to_le_bytes().to_vec(),
    ));
    r.advance(Duration::from_secs(2));
    r.m.follow(3.0, r.t, r.t).unwrap();
    r.advance(Duration::from_secs(1));
    let st = r.m.status();
    assert!(
        st.following && st.target_reached && !st.following_error,
        "{st:?}"
    );
    assert!((st.position_mm.unwrap() - 3.0).abs() < 1e-4);
}

/// Quick stop while following ends it (interrupted) and refuses follow targets until the
/// next command; re-enabled in mode 8 the drive holds where it stopped (the master keeps
/// the demand on the actual position while the drive is not enabled), and following
/// resumes. A drive fault ends following with the fault.
#[test]
fn csp_quick_stop_and_fault_end_following() {
    let mut r = csp_rig();
    r.m.follow(20.0, r.t, r.t).unwrap();
    r.advance(Duration::from_millis(200));
    assert!(r.m.status().following);
    r.ok(Command::QuickStop);
    assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
    assert_eq!(
        following_events(&r).last(),
        Some(&Event::FollowingEnded(Err(DriveError::Interrupted {
            by: "quick stop"
        })))
    );
    assert_eq!(r.m.follow(1.0, r.t, r.t), Err(DriveError::FollowDisarmed));
    let stopped = r.m.status().position_counts.unwrap();
    let start = r.log.len();
    r.ok(Command::Enable);
    r.advance(Duration::from_millis(100));
    // Every RPDO since carried the stopped position: enabling asked for no motion.
    assert!(rpdos(&r, start).iter().all(|&(_, t)| t == stopped));
    assert_eq!(r.m.status().position_counts, Some(stopped));
    assert_eq!(r.m.status().mode, Some(MODE_CSP));
    // Following again: no mode switch needed (already 8).
    let start = r.log.len();
    r.m.follow(1.0, r.t, r.t).unwrap();
    r.advance(Duration::from_secs(2));
    assert!(
        !r.frames_since(start, "601#")
            .iter()
            .any(|l| l.starts_with("601#2F6060"))
    );
    let st = r.m.status();
    assert!(st.following && st.target_reached);
    assert!((st.position_mm.unwrap() - 1.0).abs() < 1e-4);
    // A fault while following.
    r.m.follow(15.0, r.t, r.t).unwrap();
    r.advance(Duration::from_millis(100));
    r.d.inject_fault(0x7500, [0; 5], r.t);
    r.advance(Duration::from_millis(200));
    assert!(matches!(
        following_events(&r).last(),
        Some(Event::FollowingEnded(Err(DriveError::Fault { emcy: Some(e) }))) if e.code == 0x7500
    ));
    assert!(!r.m.status().following);
    r.ok(Command::FaultReset);
    r.ok(Command::Enable);
    // Home from CSP: the mode goes to 6 and back to 1 for the move.
    r.ok(Command::Home);
    assert_eq!(r.m.status().mode, Some(MODE_HOMING));
    r.ok(Command::MoveTo { target_mm: 0.5 });
    assert!((r.m.status().position_mm.unwrap() - 0.5).abs() < 1e-4);
}

/// A drive that refuses mode 8 (as the python-canopen interop drive does): following ends
/// before it starts with the drive's abort, follow targets are refused until the next
/// command, and profile position goes on working.
#[test]
fn drive_refusing_csp() {
    let mut r = csp_rig();
    r.d.refuse_sdo(Some(SdoRefusal {
        index: Some(0x6060),
        code: AbortCode::INVALID_VALUE,
    }));
    r.m.follow(3.0, r.t, r.t).unwrap();
    r.advance(Duration::from_millis(200));
    let want = DriveError::Sdo(SdoError::Aborted {
        dir: crate::canopen::sdo::Direction::Download,
        obj: ObjAddr::new(0x6060, 0),
        code: AbortCode::INVALID_VALUE,
    });
    assert_eq!(following_events(&r), vec![Event::FollowingEnded(Err(want))]);
    assert!(!r.m.status().following);
    assert_eq!(r.m.follow(3.0, r.t, r.t), Err(DriveError::FollowDisarmed));
    r.d.refuse_sdo(None);
    r.ok(Command::MoveTo { target_mm: 3.0 });
    assert_eq!(r.m.status().mode, Some(MODE_PROFILE_POSITION));
    assert!((r.m.status().position_mm.unwrap() - 3.0).abs() < 1e-4);
    // Out of the travel limits: refused at once.
    assert!(matches!(
        r.m.follow(30.0, r.t, r.t),
        Err(DriveError::OutOfLimits { .. })
    ));
}
