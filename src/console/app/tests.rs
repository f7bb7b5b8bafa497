use super::*;
use crate::service::snapshot::RunView;

fn key(c: KeyCode) -> KeyEvent {
    KeyEvent::new(c, KeyModifiers::NONE)
}
fn ch(c: char) -> KeyEvent {
    key(KeyCode::Char(c))
}
fn app() -> (App, Instant) {
    let t0 = Instant::now();
    let mut a = App::new(
        AppOptions {
            socket: "/run/axiscomp/control.sock".into(),
            jog_step_mm: 0.1,
            color: false,
        },
        t0,
    );
    a.handle_connected(
        Identity {
            user: Some("op".into()),
            role: Some(PeerRole::Operator),
        },
        t0,
    );
    (a, t0)
}

#[test]
fn tabs_by_number_tab_and_backtab() {
    let (mut a, _) = app();
    a.handle_key(ch('4'));
    assert_eq!(a.screen, Screen::Measure);
    a.handle_key(key(KeyCode::Tab));
    assert_eq!(a.screen, Screen::Results);
    a.handle_key(key(KeyCode::BackTab));
    a.handle_key(key(KeyCode::BackTab));
    assert_eq!(a.screen, Screen::Calibrate);
    a.handle_key(ch('1'));
    a.handle_key(key(KeyCode::BackTab));
    assert_eq!(a.screen, Screen::Events);
}

#[test]
fn quit_asks_while_a_run_is_active() {
    let (mut a, t0) = app();
    assert_eq!(a.handle_key(ch('q')), vec![Action::Quit]);
    a.handle_snapshot(
        Snapshot {
            run: Some(RunView {
                id: 3,
                axis: "X".into(),
                captures: 1,
                expected: 20,
                program: "twin".into(),
            }),
            ..Snapshot::default()
        },
        t0,
    );
    assert!(a.handle_key(ch('q')).is_empty());
    assert_eq!(a.overlay, Overlay::Confirm(Confirm::Quit));
    assert!(a.handle_key(ch('n')).is_empty());
    assert_eq!(a.overlay, Overlay::None);
    a.handle_key(ch('q'));
    assert_eq!(a.handle_key(ch('y')), vec![Action::Quit]);
}

#[test]
fn align_keys_send_follower_requests_with_the_step() {
    let (mut a, _) = app();
    a.handle_key(ch('2'));
    let out = a.handle_key(ch('k'));
    assert!(matches!(
        &out[..],
        [Action::Send { request: Request::Follower { action: FollowerAction::Jog, mm: Some(m) }, .. }] if (*m - 0.1).abs() < 1e-12
    ));
    a.handle_key(ch(']'));
    let out = a.handle_key(ch('j'));
    assert!(matches!(
        &out[..],
        [Action::Send { request: Request::Follower { mm: Some(m), .. }, .. }] if (*m + 1.0).abs() < 1e-12
    ));
    assert!(matches!(
        &a.handle_key(ch('z'))[..],
        [Action::Send {
            request: Request::Zero,
            ..
        }]
    ));
}

#[test]
fn viewer_keys_are_refused_locally_and_a_refusal_makes_a_viewer() {
    let (mut a, t0) = app();
    a.access = Access::Unknown;
    a.handle_key(ch('2'));
    let Action::Send { id, .. } = a.handle_key(ch('h')).remove(0) else {
        panic!()
    };
    a.handle_reply(
        id,
        Err(ClientError::Refused(
            "user ana (uid 1001) may not follower: it needs the operator role (operator_group group)".into(),
        )),
        t0,
    );
    assert!(a.read_only());
    assert!(a.handle_key(ch('h')).is_empty());
    assert!(
        a.message
            .as_ref()
            .unwrap()
            .text
            .starts_with("read-only (viewer)")
    );
    a.handle_key(ch('4'));
    assert!(a.handle_key(ch('s')).is_empty());
    assert_eq!(a.overlay, Overlay::None);
}

#[test]
fn plan_editing_with_arrows_enter_and_typing() {
    let (mut a, _) = app();
    a.handle_key(ch('4'));
    a.handle_key(key(KeyCode::Down)); // start
    a.handle_key(key(KeyCode::Down)); // end
    a.handle_key(key(KeyCode::Enter));
    for _ in 0..6 {
        a.handle_key(key(KeyCode::Backspace));
    }
    for c in "20".chars() {
        a.handle_key(ch(c));
    }
    // Digits go to the field while editing, not to the tabs.
    assert_eq!(a.screen, Screen::Measure);
    a.handle_key(key(KeyCode::Enter));
    assert_eq!(a.plan.spec.end_mm, 20.0);
    a.handle_key(key(KeyCode::Up));
    a.handle_key(key(KeyCode::Up));
    a.handle_key(key(KeyCode::Right));
    assert_eq!(a.plan.spec.axis, "Y");
    // A bad number is refused with a reason and the value kept.
    a.handle_key(key(KeyCode::Down));
    a.handle_key(key(KeyCode::Enter));
    a.handle_key(ch('x'));
    a.handle_key(key(KeyCode::Enter));
    assert!(a.message.as_ref().unwrap().text.contains("not a number"));
    a.handle_key(key(KeyCode::Esc));
    assert_eq!(a.plan.editing, None);
    assert_eq!(a.plan.spec.start_mm, 0.0);
}

#[test]
fn start_confirms_then_sends_the_plan_and_progress_gives_an_eta() {
    let (mut a, t0) = app();
    a.handle_key(ch('4'));
    a.plan.spec.end_mm = 20.0;
    a.plan.spec.targets = 5;
    a.plan.spec.runs = 2;
    assert!(a.handle_key(ch('s')).is_empty());
    assert!(matches!(a.overlay, Overlay::Confirm(Confirm::StartRun(_))));
    let out = a.handle_key(ch('y'));
    let [
        Action::Send {
            id,
            request: Request::RunStart { plan, .. },
        },
    ] = &out[..]
    else {
        panic!("{out:?}")
    };
    assert_eq!(plan.end_mm, 20.0);
    a.handle_reply(
        *id,
        Ok(serde_json::json!({"run_id": 4, "captures_expected": 20, "program": "p.nc", "cnc": "sent to the twin"})),
        t0,
    );
    let r = a.run.as_ref().unwrap();
    assert_eq!((r.run_id, r.expected), (4, Some(20)));
    assert!(r.plan.is_some());
    assert_eq!(r.eta(), None);
    let view = |captures| Snapshot {
        run: Some(RunView {
            id: 4,
            axis: "X".into(),
            captures,
            expected: 20,
            program: "p.nc".into(),
        }),
        ..Snapshot::default()
    };
    a.handle_snapshot(view(0), t0);
    a.handle_snapshot(view(5), t0 + Duration::from_secs(10));
    // Off the Measure screen, nothing polls run_status.
    a.handle_key(ch('1'));
    a.tick(t0 + Duration::from_secs(12));
    // 2 s per capture, 15 to go, 2 s since the last: 28 s.
    assert_eq!(a.run.as_ref().unwrap().eta(), Some(Duration::from_secs(28)));
    // The run ends: the console asks how.
    let out = a.handle_snapshot(Snapshot::default(), t0 + Duration::from_secs(50));
    let [
        Action::Send {
            id,
            request: Request::RunStatus,
        },
    ] = &out[..]
    else {
        panic!("{out:?}")
    };
    a.handle_reply(
        *id,
        Ok(serde_json::json!({"run_id": 4, "state": "complete", "captures": 20})),
        t0 + Duration::from_secs(50),
    );
    let r = a.run.as_ref().unwrap();
    assert_eq!((r.state.as_str(), r.captures), ("complete", 20));
    assert!(!a.run_active());
}

#[test]
fn publish_sends_confirm_only_after_the_axis_name_is_typed() {
    let (mut a, t0) = app();
    let out = a.handle_key(ch('6'));
    assert_eq!(out.len(), 2, "{out:?}");
    let Action::Send { id, .. } = &out[0] else {
        panic!()
    };
    a.handle_reply(
        *id,
        Ok(serde_json::json!({"map": "m", "tables": [{"id": 7, "name": "EXX", "kind": "positioning",
            "axis": "X", "base_axis": "X", "direction": "both", "points": 2, "start_mm": 0.0,
            "interval_mm": 10.0, "min_um": 0.0, "max_um": 1.0, "crc": "0x1", "map": "m",
            "source_run": 2, "generated_us": 0, "values_um": [0.0, 1.0]}]})),
        t0,
    );
    assert!(a.handle_key(ch('p')).is_empty());
    // A wrong name is refused; typing goes to the box, not to the tabs.
    for c in ['Y', '1'] {
        assert!(a.handle_key(ch(c)).is_empty());
    }
    assert!(a.handle_key(key(KeyCode::Enter)).is_empty());
    assert_eq!(a.screen, Screen::Publish);
    assert!(a.message.as_ref().unwrap().text.contains("\"X\""));
    a.handle_key(key(KeyCode::Backspace));
    a.handle_key(key(KeyCode::Backspace));
    a.handle_key(ch('x'));
    let out = a.handle_key(key(KeyCode::Enter));
    let [Action::Send { id, request }] = &out[..] else {
        panic!("{out:?}")
    };
    assert_eq!(
        request,
        &Request::TablePublish {
            table_id: 7,
            confirm: true
        }
    );
    assert_eq!(a.publish.publishing, Some(7));
    let out = a.handle_reply(
        *id,
        Ok(
            serde_json::json!({"table_id": 7, "target": "plc", "sequence": 4, "result": "rejected",
            "code": 3, "message": "the PLC rejected sequence 4: limits", "commit_sent": true}),
        ),
        t0,
    );
    assert_eq!(a.publish.publishing, None);
    assert!(matches!(&a.publish.outcome, Some(Ok(p)) if p.code == Some(3)));
    // The list again (the status once its outstanding request is answered).
    assert!(
        matches!(
            &out[..],
            [Action::Send {
                request: Request::TableList { .. },
                ..
            }]
        ),
        "{out:?}"
    );
}

#[test]
fn calibrate_fit_asks_then_accept_asks_and_a_viewer_cannot() {
    let (mut a, t0) = app();
    let out = a.handle_key(ch('3'));
    assert!(matches!(
        &out[..],
        [Action::Send {
            request: Request::Calibration,
            ..
        }]
    ));
    a.handle_key(ch('f'));
    for c in "/tmp/p.csv".chars() {
        a.handle_key(ch(c));
    }
    assert!(a.handle_key(key(KeyCode::Enter)).is_empty());
    assert_eq!(
        a.overlay,
        Overlay::Confirm(Confirm::Fit("/tmp/p.csv".into()))
    );
    let out = a.handle_key(ch('y'));
    let [Action::Send { id, request }] = &out[..] else {
        panic!("{out:?}")
    };
    assert_eq!(
        request,
        &Request::CalibrationFit {
            poses: "/tmp/p.csv".into()
        }
    );
    assert!(a.calibrate.fitting);
    a.handle_reply(
        *id,
        Ok(
            serde_json::json!({"pending": {"source": "/tmp/p.csv", "poses": 60, "rank": 7,
            "condition_number": 5.0, "decoupling": "model"}}),
        ),
        t0,
    );
    assert!(!a.calibrate.fitting);
    assert_eq!(a.calibrate.pending.as_ref().map(|p| p.poses), Some(60));
    assert!(a.handle_key(ch('a')).is_empty());
    let out = a.handle_key(ch('y'));
    assert!(matches!(
        &out[..],
        [Action::Send {
            request: Request::CalibrationAccept,
            ..
        }]
    ));
    a.access = Access::Viewer;
    assert!(a.handle_key(ch('f')).is_empty());
    assert_eq!(a.overlay, Overlay::None);
}

#[test]
fn w_saves_the_plans_program_to_the_typed_path() {
    let (mut a, _) = app();
    a.handle_key(ch('4'));
    a.plan.spec.end_mm = 20.0;
    a.plan.spec.targets = 5;
    a.plan.spec.runs = 2;
    assert!(a.handle_key(ch('w')).is_empty());
    for _ in 0..20 {
        a.handle_key(key(KeyCode::Backspace));
    }
    for c in "/tmp/x.nc".chars() {
        a.handle_key(ch(c));
    }
    let out = a.handle_key(key(KeyCode::Enter));
    let [Action::Save { path, text }] = &out[..] else {
        panic!("{out:?}")
    };
    assert_eq!(path, "/tmp/x.nc");
    assert_eq!(text, &a.program_text().unwrap());
    assert!(text.contains("20"), "{text}");
    a.handle_saved(path, Err("Permission denied".into()));
    assert!(
        a.message
            .as_ref()
            .unwrap()
            .text
            .contains("Permission denied")
    );
}

#[test]
fn run_status_is_polled_only_on_the_measure_screen() {
    let (mut a, t0) = app();
    assert!(a.tick(t0).is_empty());
    a.handle_key(ch('4'));
    assert_eq!(a.tick(t0).len(), 1);
    // Not again while one is outstanding, nor before the interval.
    assert!(a.tick(t0 + Duration::from_secs(5)).is_empty());
}
