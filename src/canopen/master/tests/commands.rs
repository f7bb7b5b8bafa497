//! Configure, NMT, power, homing, profile position, stops, faults, SDO, heartbeat and the
//! SYNC's pace.

use super::*;
use crate::canopen::cia402::{CW_HALT, CW_NEW_SETPOINT};
use crate::canopen::pdo::{RPDO1_MAP, TPDO1_MAP};
use crate::canopen::sdo::AbortCode;
use crate::sim::drive::SdoRefusal;

#[test]
fn configure_writes_the_pdo_mapping_and_the_drive_honours_it() {
    let mut r = Rig::default();
    let start = r.log.len();
    r.ok(Command::Configure);
    let sdo = r.frames_since(start, "601#");
    // Reset communication, boot-up, pre-operational, then SDO: first the device type.
    assert_eq!(r.log[start], "000#8201");
    assert_eq!(r.log[start + 1], "701#00");
    assert_eq!(r.log[start + 2], "000#8001");
    assert_eq!(sdo[0], "601#4000100000000000");
    // Heartbeat time 100 ms = 0x0064 as UNSIGNED16 (0x2B: 2 bytes).
    assert_eq!(sdo[1], "601#2B17100064000000");
    // RPDO1: disable (bit 31), type 1, count 0, 0x60400010, 0x607A0020, count 2, enable.
    // Bytes: command (0x23: 4 bytes, 0x2F: 1 byte), index LE, sub-index, value LE.
    assert_eq!(
        &sdo[2..9],
        &[
            "601#2300140101020080",
            "601#2F00140201000000",
            "601#2F00160000000000",
            "601#2300160110004060",
            "601#2300160220007A60",
            "601#2F00160002000000",
            "601#2300140101020000",
        ]
    );
    // TPDO1 likewise.
    assert_eq!(
        &sdo[9..16],
        &[
            "601#2300180181010080",
            "601#2F00180201000000",
            "601#2F001A0000000000",
            "601#23001A0110004160",
            "601#23001A0220006460",
            "601#2F001A0002000000",
            "601#2300180181010000",
        ]
    );
    // The twin has no PDOs 2–4: its "object does not exist" aborts are tolerated.
    assert_eq!(r.frames_since(start, "581#80011401").len(), 1);
    let s = r.d.status();
    assert_eq!(s.rpdo1_map, RPDO1_MAP.to_vec());
    assert_eq!(s.tpdo1_map, TPDO1_MAP.to_vec());
    assert!(s.rpdo1_valid && s.tpdo1_valid);
    assert_eq!(s.heartbeat_ms, 100);
    let st = r.m.status();
    assert!(st.configured && st.heartbeat_ok);
    assert_eq!(st.nmt, Some(NmtState::PreOperational));
    assert_eq!(st.state, Some(PowerState::SwitchOnDisabled));
    assert_eq!(st.position_mm, Some(0.0));
    assert!(
        r.events
            .iter()
            .any(|(_, e)| *e == Event::BootUp { expected: true })
    );
}

#[test]
fn enable_walks_shutdown_switch_on_enable_operation() {
    let mut r = Rig::default();
    r.ok(Command::Configure);
    r.ok(Command::Start);
    assert!(r.m.status().sync_running);
    assert_eq!(r.m.status().nmt, Some(NmtState::Operational));
    let start = r.log.len();
    r.ok(Command::Enable);
    // The first TPDO after the request already leads to shutdown: 0x06, 0x07, 0x0F.
    assert_eq!(r.controlwords(start), vec![0x0006, 0x0007, 0x000F]);
    assert_eq!(r.m.status().state, Some(PowerState::OperationEnabled));
    let states: Vec<PowerState> = r
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            Event::PowerState { to, .. } => Some(*to),
            _ => None,
        })
        .collect();
    assert_eq!(
        states,
        vec![
            PowerState::SwitchOnDisabled,
            PowerState::ReadyToSwitchOn,
            PowerState::SwitchedOn,
            PowerState::OperationEnabled
        ]
    );
    // Each RPDO goes out right before its SYNC.
    let i = r.log.iter().rposition(|l| l.starts_with("201#")).unwrap();
    assert_eq!(r.log[i + 1], "080#");
    let start = r.log.len();
    r.ok(Command::Disable);
    assert_eq!(r.controlwords(start), vec![0x0000]);
    assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
}

#[test]
fn homing_handshake() {
    let mut r = Rig::default();
    r.ok(Command::Configure);
    r.ok(Command::Start);
    r.ok(Command::Enable);
    // Moves are refused before homing.
    assert_eq!(
        r.run(Command::MoveTo { target_mm: 1.0 }, Duration::from_secs(1)),
        Err(DriveError::NotHomed)
    );
    let start = r.log.len();
    // Under way, the status says so and since when.
    let t0 = r.t;
    let id = r.m.submit(Command::Home, r.t);
    r.advance(Duration::from_millis(5));
    let st = r.m.status();
    assert_eq!((st.busy, st.busy_since), (Some("home"), Some(t0)));
    while r.completion(id).is_none() {
        assert!(r.t - t0 < Duration::from_secs(60), "homing not done");
        r.advance(Duration::from_millis(5));
    }
    assert_eq!(r.completion(id), Some(Ok(Reply::Done)));
    let st = r.m.status();
    assert_eq!((st.busy, st.busy_since), (None, None));
    // 0x6060 = 6 (homing) by SDO, confirmed in 0x6061; bit 4 up, then down.
    assert!(
        r.frames_since(start, "601#")
            .contains(&"601#2F60600006000000".to_string())
    );
    assert!(
        r.frames_since(start, "601#")
            .contains(&"601#4061600000000000".to_string())
    );
    assert_eq!(r.controlwords(start), vec![0x001F, 0x000F]);
    let st = r.m.status();
    assert!(st.homed);
    assert_eq!(st.mode, Some(6));
    assert_eq!(st.position_counts, Some(0));
    // The stage went from 2 mm to the switch at 0, which the plant saw.
    assert_eq!(*r.plant.lock().unwrap(), 0.0);
    assert!(r.d.status().homed);
}

#[test]
fn homing_error_is_reported() {
    let cfg = DriveConfig {
        homing: crate::canopen::HomingConfig {
            method: 0,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut r = Rig::new(cfg, TwinDriveConfig::default());
    r.ok(Command::Configure);
    r.ok(Command::Start);
    r.ok(Command::Enable);
    assert_eq!(
        r.run(Command::Home, Duration::from_secs(5)),
        Err(DriveError::Homing(HomingStatus::ErrorStopped))
    );
    // Bit 4 is not left standing.
    assert_eq!(r.m.status().controlword & CW_NEW_SETPOINT, 0);
}

#[test]
fn profile_position_handshake_and_positions() {
    let mut r = Rig::default();
    r.ready();
    let cpm = r.m.settings().counts_per_mm();
    for target in [3.0, -1.25, 7.5, 7.5, 0.0] {
        let start = r.log.len();
        let t0 = r.t;
        r.ok(Command::MoveTo { target_mm: target });
        // New set-point (bit 4) with the target, then bit 4 down after the acknowledge.
        let cws = r.controlwords(start);
        assert!(cws.ends_with(&[0x001F, 0x000F]), "{target}: {cws:?}");
        assert!(cws.iter().all(|c| [0x000F, 0x001F].contains(c)), "{cws:?}");
        let want = (target * cpm).round() as i32;
        let rpdo = format!("201#1F00{}", hex_le(want));
        assert!(r.frames_since(start, "201#1F00").contains(&rpdo), "{rpdo}");
        let st = r.m.status();
        assert!(st.target_reached);
        assert!(
            (st.position_mm.unwrap() - target).abs() <= 1.0 / cpm,
            "{st:?}"
        );
        assert_eq!(st.commanded_mm, Some(want as f64 / cpm));
        // The plant sees the stage at the commanded increment.
        assert!((*r.plant.lock().unwrap() - want as f64 / cpm).abs() < 1e-9);
        // A 10 mm/s, 100 mm/s² profile: a move over x mm takes x/10 + 0.1 s (or less).
        let took = (r.t - t0).as_secs_f64();
        assert!(took < 1.5 + 0.1 * 10.0, "{took}");
    }
}

#[test]
fn relative_jog_and_limits() {
    let mut r = Rig::default();
    r.ready();
    r.ok(Command::MoveTo { target_mm: 3.0 });
    let start = r.log.len();
    r.ok(Command::Jog { delta_mm: -1.0 });
    // Bit 6 (relative) with bit 4: 0x5F; the target is the increment.
    let cpm = r.m.settings().counts_per_mm();
    let delta = ((2.0 * cpm).round() - (3.0 * cpm).round()) as i32;
    assert!(
        r.frames_since(start, "201#5F00")
            .contains(&format!("201#5F00{}", hex_le(delta)))
    );
    assert!((r.m.status().position_mm.unwrap() - 2.0).abs() < 1e-4);
    let e = r
        .run(Command::MoveTo { target_mm: 30.0 }, Duration::from_secs(1))
        .unwrap_err();
    assert!(matches!(e, DriveError::OutOfLimits { .. }));
    assert_eq!(
        e.to_string(),
        "target 30 mm is outside the travel limits -25..25 mm"
    );
    let e = r
        .run(Command::Jog { delta_mm: -30.0 }, Duration::from_secs(1))
        .unwrap_err();
    assert!(
        matches!(e, DriveError::OutOfLimits { target_mm, .. } if (target_mm + 28.0).abs() < 1e-4)
    );
}

/// A tracker's set-point with "change set immediately" replaces a running move.
#[test]
fn change_set_immediately() {
    let mut r = Rig::default();
    r.ready();
    let id = r.m.submit(Command::MoveTo { target_mm: 10.0 }, r.t);
    r.advance(Duration::from_millis(300));
    assert!(r.completion(id).is_none());
    let start = r.log.len();
    r.ok(Command::SetTarget { target_mm: 1.0 });
    assert!(r.controlwords(start).contains(&0x003F));
    // The waiting move completes when the drive reaches the new target.
    r.advance(Duration::from_secs(3));
    assert!(r.completion(id).unwrap().is_ok());
    assert!((r.m.status().position_mm.unwrap() - 1.0).abs() < 1e-4);
}

#[test]
fn halt_and_quick_stop_preempt() {
    let mut r = Rig::default();
    r.ready();
    let id = r.m.submit(Command::MoveTo { target_mm: 20.0 }, r.t);
    r.advance(Duration::from_millis(500));
    r.ok(Command::Stop);
    assert_eq!(
        r.completion(id),
        Some(Err(DriveError::Interrupted { by: "stop" }))
    );
    let p = r.m.status().position_mm.unwrap();
    assert!(p > 2.0 && p < 10.0, "{p}");
    assert!(r.m.status().controlword & CW_HALT != 0);
    // The next move clears halt.
    r.ok(Command::MoveTo { target_mm: 1.0 });
    assert_eq!(r.m.status().controlword & CW_HALT, 0);
    let id = r.m.submit(Command::MoveTo { target_mm: 20.0 }, r.t);
    let queued = r.m.submit(Command::MoveTo { target_mm: 0.0 }, r.t);
    r.advance(Duration::from_millis(500));
    let start = r.log.len();
    r.ok(Command::QuickStop);
    assert!(r.controlwords(start).contains(&0x0002));
    assert_eq!(
        r.completion(id),
        Some(Err(DriveError::Interrupted { by: "quick stop" }))
    );
    assert_eq!(
        r.completion(queued),
        Some(Err(DriveError::Interrupted { by: "quick stop" }))
    );
    assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
    r.ok(Command::Enable);
    assert_eq!(r.m.status().state, Some(PowerState::OperationEnabled));
}

#[test]
fn drive_fault_by_emcy_then_fault_reset() {
    let mut r = Rig::default();
    r.ready();
    let id = r.m.submit(Command::MoveTo { target_mm: 15.0 }, r.t);
    r.advance(Duration::from_millis(300));
    r.d.inject_fault(0x8611, [0xDE, 0xAD, 0, 0, 1], r.t);
    r.advance(Duration::from_millis(500));
    let emcy = r
        .events
        .iter()
        .find_map(|(_, e)| match e {
            Event::Emcy(e) => Some(*e),
            _ => None,
        })
        .unwrap();
    assert_eq!(emcy.code, 0x8611);
    assert_eq!(emcy.text(), "following error");
    assert_eq!(emcy.register, 0x21);
    assert_eq!(emcy.manufacturer, [0xDE, 0xAD, 0, 0, 1]);
    let err = r.completion(id).unwrap().unwrap_err();
    assert_eq!(err, DriveError::Fault { emcy: Some(emcy) });
    assert!(err.to_string().contains("following error"), "{err}");
    let st = r.m.status();
    assert_eq!(st.state, Some(PowerState::Fault));
    assert!(st.emcy_active);
    // Fault reaction active came first.
    assert!(r.events.iter().any(|(_, e)| matches!(
        e,
        Event::PowerState {
            to: PowerState::FaultReactionActive,
            ..
        }
    )));
    // Enabling is refused while in fault.
    assert!(matches!(
        r.run(Command::Enable, Duration::from_secs(2)),
        Err(DriveError::Fault { .. })
    ));
    let start = r.log.len();
    r.ok(Command::FaultReset);
    // Bit 7 rises from 0 (a disable-voltage controlword), then drops again.
    assert_eq!(r.controlwords(start), vec![0x0000, 0x0080, 0x0000]);
    assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
    assert!(!r.m.status().emcy_active);
    assert!(
        r.events
            .iter()
            .any(|(_, e)| matches!(e, Event::Emcy(e) if e.is_reset()))
    );
    r.ok(Command::Enable);
    r.ok(Command::MoveTo { target_mm: 4.0 });
    assert!((r.m.status().position_mm.unwrap() - 4.0).abs() < 1e-4);
}

#[test]
fn heartbeat_loss_is_detected_within_the_consumer_time() {
    let mut r = Rig::default();
    r.ok(Command::Configure);
    r.ok(Command::Start);
    r.advance(Duration::from_millis(250));
    let last_hb = |r: &Rig| r.m.hb.last_heard().unwrap();
    r.d.set_heartbeat(false, r.t);
    let stopped = r.t;
    let heard = last_hb(&r);
    r.advance(Duration::from_secs(1));
    let (at, _) = r
        .events
        .iter()
        .find(|(_, e)| *e == Event::HeartbeatLost)
        .unwrap();
    // Declared lost exactly one consumer time after the last heartbeat.
    assert_eq!(r.t0 + *at, heard + Duration::from_millis(350));
    assert!(r.t0 + *at <= stopped + Duration::from_millis(350));
    assert!(!r.m.status().heartbeat_ok);
    r.d.set_heartbeat(true, r.t);
    r.advance(Duration::from_millis(200));
    assert!(r.events.iter().any(|(_, e)| *e == Event::HeartbeatResumed));
    assert!(r.m.status().heartbeat_ok);
}

#[test]
fn drive_abort_is_a_typed_error_naming_object_and_text() {
    let mut r = Rig::default();
    r.d.refuse_sdo(Some(SdoRefusal {
        index: Some(0x6081),
        code: AbortCode::VALUE_TOO_HIGH,
    }));
    let e = r
        .run(Command::Configure, Duration::from_secs(10))
        .unwrap_err();
    assert_eq!(
        e,
        DriveError::Sdo(SdoError::Aborted {
            dir: crate::canopen::sdo::Direction::Download,
            obj: ObjAddr::new(0x6081, 0),
            code: AbortCode::VALUE_TOO_HIGH,
        })
    );
    assert_eq!(
        e.to_string(),
        "SDO write of 0x6081:00: the drive aborted with 0x06090031 (value of parameter written too high (download only))"
    );
    assert!(!r.m.status().configured);
}

#[test]
fn slow_drive_times_out_and_gets_an_abort() {
    let mut r = Rig::default();
    r.d.set_sdo_delay(Duration::from_secs(2));
    let start = r.log.len();
    let e = r
        .run(
            Command::SdoRead(ObjAddr::new(0x6041, 0)),
            Duration::from_secs(5),
        )
        .unwrap_err();
    assert!(
        matches!(e, DriveError::Sdo(SdoError::Timeout { .. })),
        "{e}"
    );
    assert_eq!(
        r.frames_since(start, "601#"),
        vec!["601#4041600000000000", "601#8041600000000405"]
    );
    // The late answer arrives and is dropped; the next transfer works.
    r.d.set_sdo_delay(Duration::ZERO);
    r.advance(Duration::from_secs(3));
    let Ok(Reply::Data(d)) = r.run(
        Command::SdoRead(ObjAddr::new(0x1000, 0)),
        Duration::from_secs(1),
    ) else {
        panic!()
    };
    assert_eq!(d, 0x0002_0192u32.to_le_bytes());
}

#[test]
fn long_objects_over_sdo() {
    let mut r = Rig::default();
    let Ok(Reply::Data(name)) = r.run(
        Command::SdoRead(ObjAddr::new(0x1008, 0)),
        Duration::from_secs(1),
    ) else {
        panic!()
    };
    assert_eq!(name, crate::sim::drive::DEVICE_NAME.as_bytes());
    assert!(name.len() > 32);
    let data: Vec<u8> = (0..200u32).map(|i| (i * 7 % 251) as u8).collect();
    r.ok(Command::SdoWrite(ObjAddr::new(0x2000, 0), data.clone()));
    let Ok(Reply::Data(back)) = r.run(
        Command::SdoRead(ObjAddr::new(0x2000, 0)),
        Duration::from_secs(1),
    ) else {
        panic!()
    };
    assert_eq!(back, data);
}

#[test]
fn commands_need_the_right_state() {
    let mut r = Rig::default();
    assert_eq!(
        r.run(Command::Enable, Duration::from_secs(1)),
        Err(DriveError::NotOperational { what: "enable" })
    );
    assert_eq!(
        r.run(Command::Start, Duration::from_secs(1)),
        Err(DriveError::NotConfigured { what: "start" })
    );
    r.ok(Command::Configure);
    r.ok(Command::Start);
    assert!(matches!(
        r.run(Command::Home, Duration::from_secs(1)),
        Err(DriveError::NotEnabled { what: "home", .. })
    ));
}

#[test]
fn unexpected_reboot_forgets_the_configuration() {
    let mut r = Rig::default();
    r.ready();
    // Someone else resets the node.
    r.d.handle_frame(&CanFrame::new(0, &[0x81, 0x01]).unwrap(), r.t);
    r.advance(Duration::from_millis(50));
    assert!(
        r.events
            .iter()
            .any(|(_, e)| *e == Event::BootUp { expected: false })
    );
    let st = r.m.status();
    assert!(!st.configured && !st.homed && !st.sync_running);
    assert_eq!(st.controlword, 0);
    assert!(matches!(
        r.run(Command::MoveTo { target_mm: 1.0 }, Duration::from_secs(1)),
        Err(DriveError::NotOperational { .. })
    ));
    // Configure again and carry on.
    r.ready();
    r.ok(Command::MoveTo { target_mm: 1.0 });
}

/// A boot-up in the middle of configure (here a drive that restarts while its PDOs are
/// being written): the master settles, then configures the fresh drive from the start.
#[test]
fn configure_starts_over_after_a_boot_up() {
    let mut r = Rig::default();
    let start = r.log.len();
    let id = r.m.submit(Command::Configure, r.t);
    // Run until the RPDO mapping is being written, then reboot the drive.
    while !r.log[start..]
        .iter()
        .any(|l| l.starts_with("601#2300160110004060"))
    {
        r.advance(Duration::from_millis(1));
    }
    r.d.handle_frame(&CanFrame::new(0, &[0x82, 0x01]).unwrap(), r.t);
    r.advance(Duration::from_secs(2));
    assert!(
        matches!(r.completion(id), Some(Ok(_))),
        "{:?}",
        r.completion(id)
    );
    assert!(
        r.events
            .iter()
            .any(|(_, e)| *e == Event::BootUp { expected: false })
    );
    // The device type was read twice: configure ran again from the top.
    assert_eq!(r.frames_since(start, "601#4000100000000000").len(), 2);
    let s = r.d.status();
    assert_eq!(s.rpdo1_map, RPDO1_MAP.to_vec());
    assert!(s.rpdo1_valid && s.tpdo1_valid && r.m.status().configured);
}

#[test]
fn nmt_commands_are_confirmed_by_heartbeat() {
    let mut r = Rig::default();
    r.ok(Command::Configure);
    r.ok(Command::Start);
    r.ok(Command::Nmt(NmtCommand::StopRemoteNode));
    assert_eq!(r.m.status().nmt, Some(NmtState::Stopped));
    assert!(!r.m.status().sync_running);
    r.ok(Command::Nmt(NmtCommand::EnterPreOperational));
    assert_eq!(r.m.status().nmt, Some(NmtState::PreOperational));
    r.ok(Command::Nmt(NmtCommand::ResetNode));
    assert!(!r.m.status().configured);
}

/// At rest in profile position SYNC slows to the quiet period after `QUIET_AFTER`; a
/// command brings the full rate back before its first step needs it, and so does a
/// change the drive reports (here a fault).
#[test]
fn sync_slows_at_rest_and_any_command_or_drive_change_speeds_it_up() {
    let mut r = Rig::default();
    r.ready();
    let syncs_in = |r: &mut Rig, d: Duration| {
        let c0 = r.m.sync.count();
        r.advance(d);
        r.m.sync.count() - c0
    };
    // Homing just ended: the full rate for QUIET_AFTER, then 100 ms.
    assert!(!r.m.status().sync_quiet);
    assert_eq!(syncs_in(&mut r, Duration::from_millis(500)), 50);
    r.advance(QUIET_AFTER);
    assert!(r.m.status().sync_quiet);
    assert_eq!(syncs_in(&mut r, Duration::from_secs(1)), 10);
    let tpdos = r.m.status().tpdo_count;
    r.advance(Duration::from_millis(300));
    assert_eq!(r.m.status().tpdo_count - tpdos, 3, "the status still comes");
    // A jog: its first SYNC within one full period; 100 SYNC/s while it runs.
    let t = r.t;
    let id = r.m.submit(Command::Jog { delta_mm: 2.0 }, r.t);
    assert!(!r.m.status().sync_quiet);
    assert!(r.m.sync.poll_timeout().unwrap() <= t + Duration::from_millis(10));
    let c0 = r.m.sync.count();
    while r.completion(id).is_none() {
        r.advance(Duration::from_millis(5));
    }
    assert!(matches!(r.completion(id), Some(Ok(_))));
    let rate = (r.m.sync.count() - c0) as f64 / (r.t - t).as_secs_f64();
    assert!((rate - 100.0).abs() < 10.0, "{rate} SYNC/s during the jog");
    r.advance(QUIET_AFTER + Duration::from_millis(200));
    assert!(r.m.status().sync_quiet);
    // A fault: the EMCY ends the quiet, and its statusword comes at the full rate.
    r.d.inject_fault(0x7500, [0; 5], r.t);
    r.advance(Duration::from_millis(2));
    assert!(!r.m.status().sync_quiet);
    r.advance(Duration::from_millis(20));
    assert!(r.m.status().state.is_some_and(|s| s.is_fault()));
}
