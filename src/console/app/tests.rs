use super::*;
use crate::service::api::snapshot::RunView;

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
    assert_eq!(a.screen, Screen::Machine);
    a.handle_key(ch('7'));
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
                paused: Some("PSD1 has no spot: the run is paused".into()),
            }),
            ..Snapshot::default()
        },
        t0,
    );
    // The snapshot's reason for a pause reaches the run's progress (Measure shows it).
    assert_eq!(
        a.run.as_ref().and_then(|r| r.paused.as_deref()),
        Some("PSD1 has no spot: the run is paused")
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
    // The confirmation says the least machine time: 20 captures' dwells, plus the moves of
    // 2 runs over 0–20 mm and their overruns at the plan's feed (a few seconds).
    let text = screen_text(&a);
    let dwell_s = 20.0 * a.plan.spec.dwell_s;
    let said = text
        .split("At least ")
        .nth(1)
        .and_then(|t| t.split(" of machine time").next())
        .unwrap_or_else(|| panic!("no machine time on the confirmation:\n{text}"));
    let secs: f64 = match said.split_once(" min ") {
        Some((m, s)) => {
            m.trim().parse::<f64>().unwrap() * 60.0
                + s.trim_end_matches(" s").trim().parse::<f64>().unwrap()
        }
        None => said.trim_end_matches(" s").trim().parse().unwrap(),
    };
    assert!(
        secs >= dwell_s && secs <= dwell_s + 30.0,
        "{said}: the dwells alone are {dwell_s} s"
    );
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
            paused: None,
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
    // Once the service says what is left of the plan's motion and dwell, that is the ETA.
    a.apply_run_status(
        &serde_json::json!({"run_id": 4, "state": "running", "captures": 5, "expected": 20,
            "plan_s": 82.0, "left_s": 61.5, "machine_s": 30.0}),
        t0 + Duration::from_secs(12),
    );
    a.tick(t0 + Duration::from_secs(14));
    assert_eq!(
        a.run.as_ref().unwrap().eta(),
        Some(Duration::from_millis(59_500))
    );
    // The machine time so far: what the service said, and the 2 s since.
    assert_eq!(
        a.run.as_ref().unwrap().machine_time(),
        Some(Duration::from_secs(32))
    );
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
        Ok(
            serde_json::json!({"run_id": 4, "state": "complete", "captures": 20,
            "machine_time_s": 68.0}),
        ),
        t0 + Duration::from_secs(50),
    );
    let r = a.run.as_ref().unwrap();
    assert_eq!((r.state.as_str(), r.captures), ("complete", 20));
    // Ended: from its start to its end, as the store dated it, however long ago.
    a.tick(t0 + Duration::from_secs(90));
    let r = a.run.as_ref().unwrap();
    assert_eq!(r.machine_time(), Some(Duration::from_secs(68)));
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

/// Issue 15 at 80×24: the run picker dates the runs, and a composed table says in full what
/// it is made of (the base table, its sequence and CRC, the residual's run) beside its values.
#[test]
fn publish_at_80x24_dates_the_runs_and_shows_a_tables_composition_in_full() {
    let (mut a, t0) = app();
    let out = a.handle_key(ch('6'));
    let Action::Send { id, .. } = &out[0] else {
        panic!("{out:?}")
    };
    let composition =
        "composed: table 1 (sequence 1, CRC 0x0904CFD5) + the residual measured by run 2";
    a.handle_reply(
        *id,
        Ok(serde_json::json!({"map": "m", "tables": [{"id": 4, "name": "EXX", "kind": "positioning",
            "axis": "X", "base_axis": "X", "direction": "both", "points": 5, "start_mm": 0.0,
            "interval_mm": 2.0, "min_um": 0.0, "max_um": 3.5, "crc": "0x1", "map": "m",
            "source_run": 2, "generated_us": 0, "values_um": [0.0, -0.2, 1.4, 3.5, 3.1],
            "composition": composition}]})),
        t0,
    );
    let text = screen_text(&a);
    // The panel's rows, borders off, joined: the whole composition, word for word.
    let values: Vec<String> = text
        .lines()
        .filter_map(|l| l.split('│').nth(1).map(|c| c.trim().to_string()))
        .collect();
    assert!(values.join(" ").contains(composition), "{text}");
    for v in ["+1.40", "+3.50", "+3.10"] {
        assert!(text.contains(v), "the values still shown: {v}\n{text}");
    }
    // g: the finished runs with their date (2026-11-25 17:39:03 UTC), not the time alone.
    let out = a.handle_key(ch('g'));
    let (id, request) = sent(&out);
    assert_eq!(request, Request::Runs { limit: None });
    a.handle_reply(
        id,
        Ok(
            serde_json::json!({"runs": [{"id": 2, "axis": "X", "state": "finished",
            "created_us": 1_795_628_343_000_000i64, "updated_us": 0, "captures": 20,
            "notes": ""}]}),
        ),
        t0,
    );
    let text = screen_text(&a);
    assert!(
        text.contains("run 2    X   20 captures  2026-11-25 17:39"),
        "{text}"
    );
}

#[test]
fn calibrate_fit_asks_then_accept_asks_and_a_viewer_cannot() {
    let (mut a, t0) = app();
    let out = a.handle_key(ch('3'));
    assert!(matches!(
        &out[..],
        [
            Action::Send {
                request: Request::Calibration,
                ..
            },
            Action::Send {
                request: Request::HexapodStatus,
                ..
            }
        ]
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
            request: Request::CalibrationAccept { force: false },
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

/// The request an action sends, and its id.
fn sent(out: &[Action]) -> (u64, Request) {
    match out {
        [Action::Send { id, request }] => (*id, request.clone()),
        other => panic!("expected one request, got {other:?}"),
    }
}

/// The 80×24 screen as text.
fn screen_text(a: &App) -> String {
    use ratatui::{Terminal, backend::TestBackend};
    let mut t = Terminal::new(TestBackend::new(80, 24)).expect("terminal");
    t.draw(|f| crate::console::ui::render(f, a)).expect("draw");
    let buf = t.backend().buffer();
    (0..buf.area.height)
        .map(|y| {
            (0..buf.area.width)
                .map(|x| buf[(x, y)].symbol())
                .collect::<String>()
        })
        .collect::<Vec<_>>()
        .join("\n")
}

fn type_line(a: &mut App, text: &str) {
    for _ in 0..20 {
        a.handle_key(key(KeyCode::Backspace));
    }
    for c in text.chars() {
        a.handle_key(ch(c));
    }
    a.handle_key(key(KeyCode::Enter));
}

#[test]
fn align_reads_both_ends_types_a_target_and_shows_the_advice_in_words() {
    let (mut a, t0) = app();
    a.handle_key(ch('2'));
    // The span defaults to the Measure plan's travel (its end targets and 5 mm of overrun),
    // and is typed with s.
    assert_eq!(a.align_span(), (-5.0, 1005.0));
    a.handle_key(ch('s'));
    assert!(
        matches!(&a.overlay, Overlay::Input(i) if i.purpose == InputFor::AlignSpan && i.text == "-5 1005")
    );
    type_line(&mut a, "0 400");
    assert_eq!(a.overlay, Overlay::None);
    assert_eq!(a.align_span(), (0.0, 400.0));

    let (id, r) = sent(&a.handle_key(ch('n')));
    assert_eq!(r, Request::AlignRead { at_mm: Some(0.0) });
    a.handle_reply(
        id,
        Ok(serde_json::json!({"at_mm": 0.0, "spots": [
            {"x": -2.88, "y": -0.72, "from": "psd"},
            {"x": 0.0, "y": -0.15, "from": "psd"},
            {"x": 3.05, "y": 0.76, "from": "psd"}]})),
        t0,
    );
    let (id, r) = sent(&a.handle_key(ch('f')));
    assert_eq!(r, Request::AlignRead { at_mm: Some(400.0) });
    a.handle_reply(
        id,
        Ok(serde_json::json!({"at_mm": 400.0, "spots": [
            {"x": -5.9, "y": -1.4, "from": "psd"},
            {"x": -0.11, "y": -0.14, "from": "psd"},
            null]})),
        t0,
    );
    assert!(
        a.message.as_ref().unwrap().text.contains("no spot on PSD3"),
        "{:?}",
        a.message
    );
    assert!(
        screen_text(&a)
            .contains("at 400.0 mm: PSD1 -5.90 -1.40  PSD2 -0.11 -0.14  PSD3 no spot (t)")
    );

    // t offers the PSD with no spot; a bad line keeps the box open and says what to type.
    a.handle_key(ch('t'));
    assert!(
        matches!(&a.overlay, Overlay::Input(i) if i.purpose == InputFor::AlignTarget && i.text == "3 ")
    );
    type_line(&mut a, "4 1 2");
    assert!(matches!(a.overlay, Overlay::Input(_)));
    assert!(a.message.as_ref().unwrap().text.contains("the PSD (1–3)"));
    for _ in 0..5 {
        a.handle_key(key(KeyCode::Backspace));
    }
    for c in "3 7.5 2".chars() {
        a.handle_key(ch(c));
    }
    let (id, r) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert_eq!(
        r,
        Request::AlignTarget {
            psd: 3,
            x: 7.5,
            y: 2.0
        }
    );
    a.handle_reply(
        id,
        Ok(serde_json::json!({"at_mm": 400.0, "spots": [
            {"x": -5.9, "y": -1.4, "from": "psd"},
            {"x": -0.11, "y": -0.14, "from": "psd"},
            {"x": 7.5, "y": 2.0, "from": "target"}]})),
        t0,
    );
    assert_eq!(a.align.stations.len(), 2);
    assert!(a.align.stations[1].spots[2].unwrap().from_target);

    let (id, r) = sent(&a.handle_key(ch('a')));
    assert_eq!(
        r,
        Request::AlignAdvice {
            from_mm: 0.0,
            to_mm: 400.0,
            axis: Some("X".into())
        }
    );
    a.handle_reply(
        id,
        Ok(serde_json::json!({
            "passed": false,
            "check": "PSD3 leaves its PSD at 300 mm",
            "after": "every spot stays on its PSD from 0 to 400 mm",
            "turns": [
                {"screw": "yaw", "turns": 1.35, "text": "turn the yaw screw 1.35 turns clockwise"},
                {"screw": "pitch", "turns": -0.4, "text": "turn the pitch screw 0.40 turns anticlockwise"}],
            "misalignment_urad": [3512.4, -880.2],
            "stations": 2,
            "text": ""})),
        t0,
    );
    let s = screen_text(&a);
    for want in [
        "check not passed: PSD3 leaves its PSD at 300 mm",
        "turn the yaw screw 1.35 turns clockwise",
        "turn the pitch screw 0.40 turns anticlockwise",
        "beam to travel: yaw +3512 µrad, pitch -880 µrad",
    ] {
        assert!(s.contains(want), "no \"{want}\" in\n{s}");
    }
    assert!(!s.contains("CHECK PASSED"));

    // e clears the stations (the service's and the screen's).
    let (id, r) = sent(&a.handle_key(ch('e')));
    assert_eq!(r, Request::AlignClear);
    a.handle_reply(id, Ok(serde_json::json!({"stations": 0})), t0);
    assert!(a.align.stations.is_empty() && a.align.advice.is_none());

    let (id, _) = sent(&a.handle_key(ch('a')));
    a.handle_reply(
        id,
        Ok(serde_json::json!({
            "passed": true,
            "check": "every spot stays on its PSD from 0 to 400 mm, at least 3.10 mm inside the edge",
            "after": "", "turns": [], "misalignment_urad": [46.4, 27.3], "stations": 2, "text": ""})),
        t0,
    );
    let s = screen_text(&a);
    assert!(
        s.contains("✓ CHECK PASSED: every spot stays on its PSD from 0 to 400 mm"),
        "{s}"
    );
    assert!(s.contains("yaw +46 µrad, pitch +27 µrad"), "{s}");
    // The help lists the alignment keys.
    a.handle_key(ch('?'));
    let s = screen_text(&a);
    assert!(s.contains("read the spots at the near / far end"), "{s}");
}

#[test]
fn align_keys_are_read_only_for_a_viewer_and_a_refusal_is_said() {
    let (mut a, t0) = app();
    a.handle_key(ch('2'));
    let (id, _) = sent(&a.handle_key(ch('n')));
    a.handle_reply(
        id,
        Err(ClientError::Refused(
            "no frames from the I/O module: is the link up?".into(),
        )),
        t0,
    );
    assert!(a.message.as_ref().unwrap().text.contains("no frames"));
    assert!(a.align.stations.is_empty());
    a.access = Access::Viewer;
    for c in ['n', 'f', 't', 'a', 'e'] {
        assert!(a.handle_key(ch(c)).is_empty(), "{c}");
        assert_eq!(a.overlay, Overlay::None, "{c}");
    }
    assert!(
        a.message
            .as_ref()
            .unwrap()
            .text
            .starts_with("read-only (viewer)")
    );
}

#[test]
fn align_span_and_target_lines_are_parsed_with_errors_in_words() {
    use super::align::{parse_span, parse_target};
    assert_eq!(parse_span("0 400"), Ok((0.0, 400.0)));
    assert_eq!(parse_span("-2, 2002"), Ok((-2.0, 2002.0)));
    assert!(
        parse_span("400 0")
            .unwrap_err()
            .contains("near end must be below")
    );
    assert!(parse_span("0").unwrap_err().contains("two positions in mm"));
    assert!(
        parse_span("0 x")
            .unwrap_err()
            .contains("two positions in mm")
    );
    assert_eq!(parse_target("2 1.5 -0.5"), Ok((2, 1.5, -0.5)));
    assert_eq!(parse_target("PSD3 7 2"), Ok((3, 7.0, 2.0)));
    assert_eq!(parse_target("psd1 0 0"), Ok((1, 0.0, 0.0)));
    assert!(parse_target("SS2 1 1").is_err());
    assert!(parse_target("0 1 1").is_err());
    assert!(parse_target("2 1").is_err());
    assert!(parse_target("2 nan 1").is_err());
}

#[test]
fn a_suggested_path_is_selected_typing_replaces_it_and_ctrl_u_clears() {
    let (mut a, _) = app();
    a.handle_key(ch('3'));
    a.calibrate.fit_path = Some("/var/lib/axiscomp/poses-old.csv".into());
    a.handle_key(ch('f'));
    let text = |a: &App| match &a.overlay {
        Overlay::Input(i) => i.text.clone(),
        o => panic!("{o:?}"),
    };
    assert_eq!(text(&a), "/var/lib/axiscomp/poses-old.csv");
    assert!(a.input_fresh);
    // The first character replaces the suggestion; then typing appends.
    a.handle_key(ch('/'));
    a.handle_key(ch('t'));
    assert_eq!(text(&a), "/t");
    a.handle_key(key(KeyCode::Backspace));
    assert_eq!(text(&a), "/");
    // Ctrl-U clears what was typed.
    a.handle_key(ch('x'));
    a.handle_key(KeyEvent::new(KeyCode::Char('u'), KeyModifiers::CONTROL));
    assert_eq!(text(&a), "");
    // Esc, and the box opens selected again: Backspace clears the suggestion at once.
    a.handle_key(key(KeyCode::Esc));
    a.handle_key(ch('f'));
    assert!(a.input_fresh);
    a.handle_key(key(KeyCode::Backspace));
    assert_eq!(text(&a), "");
}

/// The follower map on the Align screen at 80×24 (issue 14): `i` imports a certificate by its
/// path on the service's host, `m` types the span, passes and frames and asks, then the
/// mapping's progress and time left come from the snapshots, `m` again asks to stop it, and
/// the map made is summarised; `v` switches back to the beam alignment.
#[test]
fn align_imports_a_certificate_maps_the_follower_and_shows_progress_at_80x24() {
    use crate::service::api::CertificateImport;
    use crate::service::api::{MappingRequest, MappingView};
    let (mut a, t0) = app();
    a.handle_key(ch('2'));
    assert_eq!(a.follower.panel, AlignPanel::Beam);
    // The certificate.
    a.handle_key(ch('i'));
    assert!(matches!(&a.overlay, Overlay::Input(i) if i.purpose == InputFor::CertificatePath));
    assert!(screen_text(&a).contains("Import the follower's certificate"));
    for c in "/var/lib/axiscomp/stage-7.csv".chars() {
        a.handle_key(ch(c));
    }
    let (id, r) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert_eq!(
        r,
        Request::FollowerCertificate(CertificateImport {
            path: Some("/var/lib/axiscomp/stage-7.csv".into()),
            ..CertificateImport::default()
        })
    );
    a.handle_reply(
        id,
        Ok(serde_json::json!({"id": 3, "name": "stage-7.csv", "in_use": true,
            "summary": ["span 0.0 to 400.0 mm", "long-wavelength positioning: 3.18 µm range, u ≤ 0.14 µm, from the certificate stage-7.csv"]})),
        t0,
    );
    let m = a
        .message
        .as_ref()
        .map(|m| m.text.clone())
        .unwrap_or_default();
    assert_eq!(
        m,
        "certificate imported: map 3 in use; take the zero again (z)"
    );
    let t = screen_text(&a);
    assert!(
        t.contains("Follower map: i certificate  m map / stop  l level  u check  v alignment"),
        "{t}"
    );
    assert!(t.contains("map 3 (stage-7.csv):"), "{t}");
    assert!(
        t.contains("long-wavelength positioning: 3.18 µm range"),
        "{t}"
    );
    // The mapping: the span typed (the alignment's by default), then asked.
    a.handle_key(ch('m'));
    assert!(
        matches!(&a.overlay, Overlay::Input(i) if i.purpose == InputFor::Mapping && i.text == "-5 1005 4 1000"),
        "{:?}",
        a.overlay
    );
    type_line(&mut a, "0 400 2 500");
    let want = MappingRequest {
        from_mm: Some(0.0),
        to_mm: Some(400.0),
        passes: Some(2),
        frames: Some(500),
        ..MappingRequest::default()
    };
    assert_eq!(a.overlay, Overlay::Confirm(Confirm::MapStart(want.clone())));
    let t = screen_text(&a);
    assert!(t.contains("Map the follower?"), "{t}");
    assert!(
        t.contains("Stop-and-go over 0–400 mm in 3.75 mm steps:"),
        "{t}"
    );
    assert!(t.contains("2 passes, 500 frames a side."), "{t}");
    let (id, r) = sent(&a.handle_key(ch('y')));
    assert_eq!(r, Request::FollowerMapStart(want));
    a.handle_reply(
        id,
        Ok(
            serde_json::json!({"state": "approaching", "stops_planned": 226, "dwell_s": 3.1,
            "cnc": "sent to the twin's CNC at 127.0.0.1:5099"}),
        ),
        t0,
    );
    assert!(a.message.as_ref().is_some_and(|m| m.text
        == "follower mapping started: 226 stops, dwell 3.1 s; sent to the twin's CNC at 127.0.0.1:5099"));
    // Progress from the snapshot.
    let view = MappingView {
        state: "mapping".into(),
        axis: "X".into(),
        from_mm: 0.0,
        to_mm: 400.0,
        step_mm: 3.75,
        passes: 2,
        frames: 500,
        stops_done: 57,
        stops_planned: 226,
        steps_kept: 56,
        skipped: 1,
        elapsed_s: 201.0,
        left_s: 612.0,
        dwell_s: 3.1,
        cnc: "sent to the twin's CNC at 127.0.0.1:5099".into(),
        ..MappingView::default()
    };
    a.handle_snapshot(
        Snapshot {
            follower_mapping: Some(view.clone()),
            ..Snapshot::default()
        },
        t0,
    );
    assert_eq!(a.follower.panel, AlignPanel::Follower);
    let t = screen_text(&a);
    assert!(
        t.contains("mapping stop 57 of 226 ███░░░░░░░ 56 kept, 1 skipped"),
        "{t}"
    );
    assert!(
        t.contains("3.4 min of machine time, 10.2 min left; dwell 3.1 s a stop"),
        "{t}"
    );
    // m now asks to stop it.
    a.handle_key(ch('m'));
    assert_eq!(a.overlay, Overlay::Confirm(Confirm::MapStop));
    assert!(screen_text(&a).contains("Stop the follower mapping?"));
    let (_, r) = sent(&a.handle_key(ch('y')));
    assert_eq!(r, Request::FollowerMapStop);
    // It ended (done here): said, and the map made summarised.
    a.handle_snapshot(
        Snapshot {
            follower_mapping: Some(MappingView {
                state: "done".into(),
                stops_done: 226,
                steps_kept: 224,
                left_s: 0.0,
                map_id: Some(4),
                summary: vec![
                    "span -10.0 to 1010.0 mm".into(),
                    "vertical straightness (to the end-point line): 1.33 µm range over 108 points, u ≤ 0.16 µm, from the self-calibration; PSD2's jump took a line of 7.0 µm/m".into(),
                ],
                ..view
            }),
            ..Snapshot::default()
        },
        t0,
    );
    assert!(a.message.as_ref().is_some_and(
        |m| m.text == "follower mapped: map 4 in use (224 steps), the zero taken again"
    ));
    let t = screen_text(&a);
    assert!(t.contains("map 4 made and in use:"), "{t}");
    assert!(
        t.contains("vertical straightness (to the end-point line): 1.33 µm range"),
        "{t}"
    );
    // The help fits 80×24 with every key of the screen and the global ones.
    a.handle_key(ch('?'));
    let t = screen_text(&a);
    assert!(
        t.contains("panel: follower map / beam alignment")
            && t.contains("any key closes this help"),
        "{t}"
    );
    a.handle_key(ch('x'));
    // v: back to the beam alignment.
    a.handle_key(ch('v'));
    assert!(screen_text(&a).contains("Beam alignment over the travel"));
    // A bad mapping line is said in words, the box stays.
    a.handle_key(ch('m'));
    type_line(&mut a, "400 0");
    assert!(matches!(&a.overlay, Overlay::Input(_)));
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text == "span 400–0 mm: the near end must be below the far end")
    );
    assert!(
        parse_mapping("0 400 two")
            .unwrap_err()
            .contains("e.g. 0 400 2 500")
    );
}

#[test]
fn align_starts_the_level_stations_takes_a_typed_reading_and_stops_them() {
    use crate::service::api::{LevelRequest, LevelView, StationView};
    let (mut a, t0) = app();
    a.handle_key(ch('2'));
    // L with nothing under way: said, nothing sent.
    assert!(a.handle_key(ch('L')).is_empty());
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text == "no level stations are under way")
    );
    // l asks, then starts them over the map's span.
    a.handle_key(ch('l'));
    assert_eq!(a.overlay, Overlay::Confirm(Confirm::LevelStart));
    assert!(screen_text(&a).contains("Read the level at stations?"));
    let (id, r) = sent(&a.handle_key(ch('y')));
    assert_eq!(r, Request::FollowerLevelStart(LevelRequest::default()));
    a.handle_reply(
        id,
        Ok(
            serde_json::json!({"state": "stations", "stations": [{}, {}, {}], "dwell_s": 25.5,
            "cnc": "load the program on the CNC and start it"}),
        ),
        t0,
    );
    assert!(a.message.as_ref().is_some_and(|m| m.text
        == "level stations started: 3 stations, dwell 25.5 s; load the program on the CNC and start it"));
    // A station awaits the level's reading: shown, and l opens the box for it.
    let station = |state: &str| StationView {
        state: state.into(),
        ..StationView::default()
    };
    let view = LevelView {
        state: "stations".into(),
        level: "manual".into(),
        stations: vec![
            station("taken"),
            station("awaiting the level"),
            station("waiting"),
        ],
        taken: 1,
        current: Some(1),
        awaiting_reading: Some(1),
        prompt: "station 2 of 3 at 100.0 mm: read the level and type its reading (arcsec)".into(),
        elapsed_s: 95.0,
        ..LevelView::default()
    };
    a.handle_snapshot(
        Snapshot {
            follower_level: Some(view.clone()),
            ..Snapshot::default()
        },
        t0,
    );
    assert_eq!(a.follower.panel, AlignPanel::Follower);
    let t = screen_text(&a);
    assert!(t.contains("level stations 1 of 3 stations"), "{t}");
    assert!(
        t.contains("station 2 of 3 at 100.0 mm: read the level"),
        "{t}"
    );
    a.handle_key(ch('l'));
    assert!(
        matches!(&a.overlay, Overlay::Input(i) if i.purpose == InputFor::LevelReading),
        "{:?}",
        a.overlay
    );
    assert!(screen_text(&a).contains("The level's reading"));
    type_line(&mut a, "one");
    assert!(matches!(&a.overlay, Overlay::Input(_)));
    assert!(a.message.as_ref().is_some_and(
        |m| m.text == "level reading \"one\": type the level's reading in arcsec, e.g. -1.25"
    ));
    a.handle_key(key(KeyCode::Esc));
    a.handle_key(ch('l'));
    for c in "-1.25".chars() {
        a.handle_key(ch(c));
    }
    let (id, r) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert_eq!(
        r,
        Request::FollowerLevelReading {
            arcsec: serde_json::json!(-1.25)
        }
    );
    a.handle_reply(
        id,
        Ok(serde_json::json!({"station": 2, "arcsec": -1.25})),
        t0,
    );
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text == "the level's reading -1.25″ taken at station 2")
    );
    // No reading awaited: l (or L) asks to stop them.
    a.handle_snapshot(
        Snapshot {
            follower_level: Some(LevelView {
                awaiting_reading: None,
                ..view.clone()
            }),
            ..Snapshot::default()
        },
        t0,
    );
    a.handle_key(ch('l'));
    assert_eq!(a.overlay, Overlay::Confirm(Confirm::LevelStop));
    assert!(screen_text(&a).contains("Stop the level stations?"));
    let (_, r) = sent(&a.handle_key(ch('y')));
    assert_eq!(r, Request::FollowerLevelStop);
    // Done: said, the map made summarised.
    a.handle_snapshot(
        Snapshot {
            follower_level: Some(LevelView {
                state: "done".into(),
                taken: 3,
                map_id: Some(6),
                summary: vec!["vertical (to the first point): 1.10 µm range".into()],
                prompt: String::new(),
                ..view
            }),
            ..Snapshot::default()
        },
        t0,
    );
    assert!(a.message.as_ref().is_some_and(
        |m| m.text == "level stations done: map 6 in use (3 stations), the zero taken again"
    ));
    let t = screen_text(&a);
    assert!(t.contains("map 6 fitted with the level and in use:"), "{t}");
    assert_eq!(parse_level_reading(" 0.5″ "), Ok(0.5));
    assert!(parse_level_reading("NaN").is_err());
}

#[test]
fn align_checks_the_map_in_use_on_this_set_up_with_u() {
    use crate::service::api::{LevelRequest, LevelView};
    let (mut a, t0) = app();
    a.handle_key(ch('2'));
    // u asks, in its own words, then starts the stations as a check of the map in use.
    a.handle_key(ch('u'));
    assert_eq!(a.overlay, Overlay::Confirm(Confirm::LevelCheck));
    let text = screen_text(&a);
    assert!(
        text.contains("Check the map in use on this set-up?")
            && text.contains("the map in use stays."),
        "{text}"
    );
    let (id, r) = sent(&a.handle_key(ch('y')));
    assert_eq!(
        r,
        Request::FollowerLevelStart(LevelRequest {
            check_map: true,
            ..LevelRequest::default()
        })
    );
    a.handle_reply(
        id,
        Ok(
            serde_json::json!({"state": "stations", "stations": [{}, {}, {}, {}, {}, {}],
            "dwell_s": 25.5, "cnc": "sent to the twin's CNC"}),
        ),
        t0,
    );
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text.starts_with("level stations started: 6 stations"))
    );
    // Under way: u says so and sends nothing.
    a.handle_snapshot(
        Snapshot {
            follower_level: Some(LevelView {
                state: "stations".into(),
                check_map: true,
                ..LevelView::default()
            }),
            ..Snapshot::default()
        },
        t0,
    );
    assert!(a.handle_key(ch('u')).is_empty());
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text.starts_with("the level stations are under way"))
    );
}

#[test]
fn machine_screen_walks_the_plan_and_attaches_the_picked_run_to_the_next_set_up() {
    let (mut a, t0) = app();
    let (id, req) = sent(&a.handle_key(ch('8')));
    assert_eq!(req, Request::Machine { id: None });
    let setup = |n: usize, axis: &str, state: &str, run: Option<i64>| {
        serde_json::json!({"number": n, "title": format!("{n} of 4"), "axis": axis,
            "state": state, "run_id": run, "steps": [format!("step of {n}")],
            "plan": {"axis": axis, "start_mm": 0.0, "end_mm": 500.0, "targets": 26, "runs": 2,
                "overrun_mm": 2.0, "dwell_s": 2.0, "feed_mm_min": 6000.0, "lead_mm": 10.0},
            "run_notes": format!("machine 2, set-up {n} of 4")})
    };
    let view = |setups: Vec<serde_json::Value>| {
        serde_json::json!({"id": 2, "name": "VMC", "chain": "X Y bed Z",
            "travel_mm": [1000.0, 600.0, 500.0], "tool_mm": [0.0, 0.0, -150.0],
            "created": "2026-11-30T00:00:00Z", "setups": setups, "squareness": [],
            "no_model": "2 to go"})
    };
    a.handle_reply(
        id,
        Ok(view(vec![
            setup(1, "X", "measured", Some(1)),
            setup(2, "Y", "measured", Some(2)),
            setup(3, "Z", "next", None),
            setup(4, "Z", "waiting", None),
        ])),
        t0,
    );
    // The steps shown are the next set-up's.
    assert_eq!(a.machine.selected, 2);
    assert_eq!(a.machine.next().map(|s| s.number), Some(3));
    let text = screen_text(&a);
    for want in [
        "8 Machine",
        "Machine 2: VMC",
        "3 of 4",
        "▶ next",
        "step of 3",
        "2 to go",
    ] {
        assert!(text.contains(want), "{want} not on\n{text}");
    }
    // p: the set-up's run into the Measure screen's form; back to the Machine screen.
    a.handle_key(ch('p'));
    assert_eq!(a.screen, Screen::Measure);
    assert_eq!((a.plan.spec.axis.as_str(), a.plan.spec.targets), ("Z", 26));
    // Started from there, the run's notes name the set-up (not once its axis changed).
    assert_eq!(
        a.plan.notes_for(&a.plan.spec).as_deref(),
        Some("machine 2, set-up 3 of 4")
    );
    let mut other = a.plan.spec.clone();
    other.axis = "X".into();
    assert_eq!(a.plan.notes_for(&other), None);
    a.handle_key(ch('8'));
    // a: the runs are asked for; the picker offers the finished runs of Z not attached.
    let (id, req) = sent(&a.handle_key(ch('a')));
    assert_eq!(req, Request::Runs { limit: None });
    let run = |id: i64, axis: &str, state: &str| {
        serde_json::json!({"id": id, "date": "", "created_us": 0, "axis": axis, "plan": "",
            "updated_us": 0, "captures": 52, "notes": "", "tables_active": "none", "state": state})
    };
    a.handle_reply(
        id,
        Ok(
            serde_json::json!({"runs": [run(5, "Z", "running"), run(4, "Z", "finished"),
            run(3, "Z", "finished"), run(2, "Y", "finished"), run(1, "X", "finished")]}),
        ),
        t0,
    );
    let offered: Vec<i64> = a.machine.runs(&a.results).iter().map(|r| r.id).collect();
    assert_eq!(offered, [4, 3]);
    // Down to run 3, Enter: attached to set-up 3 of machine 2.
    a.handle_key(key(KeyCode::Down));
    let (id, req) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert_eq!(
        req,
        Request::MachineAttach {
            id: 2,
            setup: 3,
            run_id: 3
        }
    );
    // While it is attached, a second a waits.
    assert!(a.handle_key(ch('a')).is_empty());
    // Attached: the machine is asked for again, and the steps follow the plan to set-up 4.
    let (id, req) = sent(&a.handle_reply(id, Ok(view(vec![])), t0));
    assert_eq!(req, Request::Machine { id: Some(2) });
    a.handle_reply(
        id,
        Ok(view(vec![
            setup(1, "X", "measured", Some(1)),
            setup(2, "Y", "measured", Some(2)),
            setup(3, "Z", "measured", Some(3)),
            setup(4, "Z", "next", None),
        ])),
        t0,
    );
    assert_eq!(a.machine.selected, 3);
    // A refusal is said, and the plan stays.
    let (id, _) = sent(&a.handle_key(ch('a')));
    a.handle_reply(
        id,
        Ok(serde_json::json!({"runs": [run(4, "Z", "finished")]})),
        t0,
    );
    let (id, req) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert_eq!(
        req,
        Request::MachineAttach {
            id: 2,
            setup: 4,
            run_id: 4
        }
    );
    let why = "run 4 has flags open (1 capture): retake or exclude them first (run flags) (machine 2, set-up 4 of 4)";
    assert!(
        a.handle_reply(id, Err(ClientError::Refused(why.into())), t0)
            .is_empty()
    );
    assert_eq!(a.machine.attaching, None);
    assert_eq!(a.message.as_ref().map(|m| m.text.as_str()), Some(why));
    assert_eq!(a.machine.next().map(|s| s.number), Some(4));
}

#[test]
fn machine_screen_detaches_the_selected_set_up_and_those_after_it_once_asked() {
    let (mut a, t0) = app();
    let (id, _) = sent(&a.handle_key(ch('8')));
    let setup = |n: usize, state: &str, run: Option<i64>| {
        serde_json::json!({"number": n, "title": format!("{n} of 4"), "axis": "X",
            "state": state, "run_id": run, "steps": [],
            "plan": {"axis": "X", "start_mm": 0.0, "end_mm": 500.0, "targets": 26, "runs": 2,
                "overrun_mm": 2.0, "dwell_s": 2.0, "feed_mm_min": 6000.0, "lead_mm": 10.0},
            "run_notes": ""})
    };
    let view = |setups: Vec<serde_json::Value>| {
        serde_json::json!({"id": 7, "name": "VMC", "chain": "X Y bed Z",
            "travel_mm": [1000.0, 600.0, 500.0], "tool_mm": [0.0, 0.0, -150.0],
            "created": "2026-11-30T00:00:00Z", "setups": setups, "squareness": [],
            "no_model": "1 to go"})
    };
    a.handle_reply(
        id,
        Ok(view(vec![
            setup(1, "measured", Some(11)),
            setup(2, "measured", Some(12)),
            setup(3, "measured", Some(13)),
            setup(4, "next", None),
        ])),
        t0,
    );
    assert_eq!(a.machine.selected, 3);
    // The next set-up has no run: nothing to ask.
    assert!(a.handle_key(ch('d')).is_empty());
    assert_eq!(a.overlay, Overlay::None);
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text == "set-up 4 of 4 has no run to detach"),
        "{:?}",
        a.message
    );
    // Set-up 2 selected: asked first, naming the runs that go.
    a.handle_key(key(KeyCode::Up));
    a.handle_key(key(KeyCode::Up));
    assert!(a.handle_key(ch('d')).is_empty());
    assert_eq!(
        a.overlay,
        Overlay::Confirm(Confirm::Detach {
            id: 7,
            setup: 2,
            runs: vec![12, 13]
        })
    );
    let text = screen_text(&a);
    assert!(
        text.contains("Runs 12, 13 leave set-up 2 of machine 7"),
        "{text}"
    );
    // n keeps everything; d then y sends the request.
    assert!(a.handle_key(ch('n')).is_empty());
    assert_eq!(a.overlay, Overlay::None);
    a.handle_key(ch('d'));
    let (id, req) = sent(&a.handle_key(ch('y')));
    assert_eq!(req, Request::MachineDetach { id: 7, setup: 2 });
    // Done: the machine is asked for again.
    let (_, req) = sent(&a.handle_reply(id, Ok(view(vec![])), t0));
    assert_eq!(req, Request::Machine { id: Some(7) });
    assert!(
        a.message
            .as_ref()
            .is_some_and(|m| m.text.starts_with("detached from set-up 2 on"))
    );
}

#[test]
fn machine_screen_stores_a_new_machine_from_its_record_on_the_service_s_host() {
    let (mut a, t0) = app();
    let (id, _) = sent(&a.handle_key(ch('8')));
    // No machine stored yet: the screen says how to store one.
    a.handle_reply(
        id,
        Err(ClientError::Refused("no machine is stored".into())),
        t0,
    );
    assert!(screen_text(&a).contains("n and its path"));
    assert!(a.handle_key(ch('n')).is_empty());
    assert!(matches!(&a.overlay, Overlay::Input(i) if i.purpose == InputFor::MachineRecord));
    // Empty: asked again, nothing sent.
    assert!(a.handle_key(key(KeyCode::Enter)).is_empty());
    for c in "/srv/vmc.toml".chars() {
        a.handle_key(ch(c));
    }
    let (id, req) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert_eq!(
        req,
        Request::MachineNew {
            record: String::new(),
            path: Some("/srv/vmc.toml".into()),
            origin: None
        }
    );
    let setup = |n: usize, state: &str| {
        serde_json::json!({"number": n, "title": format!("{n} of 4"), "axis": "X",
            "state": state, "run_id": null, "steps": [format!("step of {n}")],
            "plan": {"axis": "X", "start_mm": 0.0, "end_mm": 500.0, "targets": 26, "runs": 2,
                "overrun_mm": 2.0, "dwell_s": 2.0, "feed_mm_min": 6000.0, "lead_mm": 10.0},
            "run_notes": ""})
    };
    let view = serde_json::json!({"id": 3, "name": "VMC 1000", "chain": "X Y bed Z",
        "travel_mm": [1000.0, 600.0, 500.0], "tool_mm": [0.0, 0.0, -150.0],
        "created": "2026-11-30T00:00:00Z",
        "setups": [setup(1, "next"), setup(2, "waiting"), setup(3, "waiting"), setup(4, "waiting")],
        "squareness": [], "no_model": "4 to go"});
    assert!(a.handle_reply(id, Ok(view), t0).is_empty());
    assert_eq!(a.machine.view.as_ref().map(|v| v.id), Some(3));
    assert_eq!(a.machine.selected, 0);
    assert_eq!(
        a.message.as_ref().map(|m| m.text.as_str()),
        Some("machine 3 (VMC 1000) stored: its plan starts with set-up 1")
    );
    assert!(screen_text(&a).contains("step of 1"));
    // A record the service refuses: said as the service says it.
    a.handle_key(ch('n'));
    for c in "/srv/bad.toml".chars() {
        a.handle_key(ch(c));
    }
    let (id, _) = sent(&a.handle_key(key(KeyCode::Enter)));
    let why = "/srv/bad.toml: \"travel_mm\": 3 numbers (X, Y, Z) in mm";
    a.handle_reply(id, Err(ClientError::Refused(why.into())), t0);
    assert_eq!(a.message.as_ref().map(|m| m.text.as_str()), Some(why));
    assert_eq!(a.machine.view.as_ref().map(|v| v.id), Some(3));
}

/// Issue 29 at 80×24: a refusal too long for one row wraps onto the status bar's next rows
/// instead of losing its end (a missing certificate read `cannot read it (No such`; a mapping
/// too short for its fit lost the reason "it needs at least 11").
#[test]
fn a_long_refusal_is_read_to_its_end_at_80x24() {
    let (mut a, t0) = app();
    a.handle_key(ch('2'));
    a.handle_key(ch('i'));
    for c in "/srv/certs/stage-0421.csv".chars() {
        a.handle_key(ch(c));
    }
    // The service's own words for a file it cannot open.
    let why = "the certificate /srv/certs/stage-0421.csv: cannot read it (No such file or directory (os error 2)): check the path on the service's host";
    let (id, request) = sent(&a.handle_key(key(KeyCode::Enter)));
    assert!(
        matches!(request, Request::FollowerCertificate(_)),
        "{request:?}"
    );
    a.handle_reply(id, Err(ClientError::Refused(why.into())), t0);
    let text = screen_text(&a);
    let flat: String = text
        .lines()
        .rev()
        .take(3)
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .map(str::trim)
        .collect::<Vec<_>>()
        .join(" ");
    assert!(
        flat.contains("(os error 2)): check the path on the service's host"),
        "the end of the refusal is not on the status bar:\n{text}"
    );
    // The screen keeps its tabs and its title row.
    assert!(
        text.lines().next().unwrap_or_default().contains("1 Live"),
        "{text}"
    );
}

fn requests(out: &[Action]) -> Vec<(u64, Request)> {
    out.iter()
        .filter_map(|a| match a {
            Action::Send { id, request } => Some((*id, request.clone())),
            _ => None,
        })
        .collect()
}

/// Issue 29: what the store holds is read again after a restart. Align showed "no advice yet"
/// while a passed alignment was stored and used by the pre-run check; Publish said "no stored
/// tables" after `table generate` from the command line until `r`.
#[test]
fn align_and_publish_show_what_the_store_holds_after_a_restart() {
    let (mut a, t0) = app();
    let asked = |out: &[Action]| {
        requests(out)
            .into_iter()
            .find(|(_, r)| matches!(r, Request::AlignStored { .. }))
    };
    let (id, request) = asked(&a.handle_key(ch('2'))).expect("the stored alignment asked for");
    assert_eq!(
        request,
        Request::AlignStored {
            axis: Some("X".into())
        }
    );
    // Asked once, not at every tick.
    assert!(asked(&a.tick(t0 + Duration::from_secs(1))).is_none());
    a.handle_reply(
        id,
        Ok(serde_json::json!({"axis": "X", "alignment_id": 3, "unix_us": 1_700_000_000_000_000i64,
            "from_mm": -1.0, "to_mm": 400.0, "passed": true,
            "check": "every spot stays on its PSD from -1 to 400 mm, at least 4.40 mm inside the edge",
            "after": "", "turns": [], "misalignment_urad": [20.0, 20.0], "stations": 2})),
        t0,
    );
    let text = screen_text(&a);
    assert!(
        text.contains("stored alignment of X over -1–400 mm, 2023-11-14")
            && text.contains("✓ CHECK PASSED: every spot stays on its PSD")
            && text.contains("beam to travel: yaw +20 µrad, pitch +20 µrad")
            && !text.contains("no advice yet"),
        "{text}"
    );
    // Once a station is read the operator is on a new round: the stored one steps aside.
    a.align.stations.push(StationView {
        at_mm: -1.0,
        spots: [None; 3],
    });
    let text = screen_text(&a);
    assert!(
        text.contains("no advice yet") && !text.contains("stored alignment"),
        "{text}"
    );
    a.align.stations.clear();
    // The service restarts: the console asks again when it is back.
    a.handle_down(
        &ClientError::Closed,
        Duration::from_millis(100),
        t0 + Duration::from_secs(2),
    );
    a.handle_connected(
        Identity {
            user: Some("op".into()),
            role: Some(PeerRole::Operator),
        },
        t0 + Duration::from_secs(3),
    );
    let (id, _) =
        asked(&a.tick(t0 + Duration::from_secs(3))).expect("asked again after the restart");
    a.handle_reply(id, Ok(serde_json::Value::Null), t0);
    let text = screen_text(&a);
    assert!(
        text.contains("no advice yet") && text.contains("no alignment of X stored"),
        "{text}"
    );
    // Publish lists the tables each time it is opened.
    let listed = |out: &[Action]| {
        requests(out)
            .iter()
            .any(|(_, r)| matches!(r, Request::TableList { .. }))
    };
    let out = a.handle_key(ch('6'));
    assert!(listed(&out), "{out:?}");
    for (id, r) in requests(&out) {
        let v = match r {
            Request::TableList { .. } => serde_json::json!({"map": "m", "tables": []}),
            _ => serde_json::json!({}),
        };
        a.handle_reply(id, Ok(v), t0);
    }
    assert!(!listed(&a.tick(t0 + Duration::from_secs(4))));
    a.handle_key(ch('1'));
    assert!(listed(&a.handle_key(ch('6'))), "Publish opened again");
}

/// Issue 29: a homing after a restart takes up to a minute; Live and Align say it is under
/// way and for how long (they said "NOT homed" meanwhile).
#[test]
fn a_homing_under_way_says_how_long_it_has_been_going() {
    use crate::service::api::snapshot::FollowerView;
    let (mut a, t0) = app();
    let follower = |busy: Option<&str>, busy_s: Option<f64>| Snapshot {
        follower: FollowerView {
            state: "Operation enabled".into(),
            homed: false,
            heartbeat_ok: true,
            busy: busy.map(str::to_string),
            busy_s,
            ..FollowerView::default()
        },
        ..Snapshot::default()
    };
    a.handle_snapshot(follower(Some("home"), Some(12.6)), t0);
    for screen in ['1', '2'] {
        a.handle_key(ch(screen));
        let text = screen_text(&a);
        assert!(
            text.contains("homing for 12 s") && !text.contains("NOT homed"),
            "screen {screen}:\n{text}"
        );
    }
    // Another command under way, or none: not homed, as before.
    a.handle_snapshot(follower(Some("move"), Some(1.0)), t0);
    assert!(screen_text(&a).contains("NOT homed (h)"));
    a.handle_key(ch('1'));
    a.handle_snapshot(follower(None, None), t0);
    assert!(screen_text(&a).contains("NOT homed"));
}
