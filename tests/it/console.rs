//! The console (`axiscomp console`, issue 6).
//!
//! Render tests: every screen at 80×24 and 160×48 into ratatui's `TestBackend`, the buffer's
//! text under insta. The data is a real twin + service session kept as a fixture
//! (`fixtures/console_twin.json`, recorded by `capture_console_fixture` below), because a live
//! snapshot's noise digits cannot be rounded away deterministically (a value near a rounding
//! boundary flips between runs). The session: the follower homed, `nominal 0` and `zero` at
//! rest, PSD3 blocked and unblocked (a cleared `beam-blocked` alarm); run 1 of the short plan
//! to the end; run 2 of the same plan, recorded snapshot by snapshot, with the service's
//! `run_result` half-way (the live plot) and at the end, the `runs` list and run 1's result
//! (for the before/after comparison), and the audit log. What the fixture redacts: every timestamp is shifted by
//! one offset so the rest snapshot is at 2026-01-01 08:00:00 UTC, and the program paths are
//! moved out of the temporary directory; nothing else is changed.
//!
//! The app is fed the fixture exactly as the loop feeds it live data: the plan typed by keys,
//! each request it sends answered with the service's recorded reply.
//!
//! The key-driven test then runs the real console loop against a live service and twin: plan →
//! start → progress → results, and an abort.

use crate::helpers::{RigOptions, ServiceRig, short_plan, within_s};
use axiscomp::console::app::{Access, Action, App, AppOptions, Field, LinkState, Screen};
use axiscomp::console::client::{Client, ClientError, ClientOptions, Identity, PeerRole};
use axiscomp::console::{drive, ui};
use axiscomp::run::PlanSpec;
use axiscomp::service::api::Request;
use axiscomp::service::api::snapshot::Snapshot;
use crossterm::event::{Event, KeyCode, KeyEvent, KeyModifiers};
use futures_util::StreamExt;
use ratatui::Terminal;
use ratatui::backend::TestBackend;
use ratatui::buffer::Buffer;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::path::Path;
use std::time::{Duration, Instant};

const FIXTURE: &str = "tests/it/fixtures/console_twin.json";

/// Handovers and captures quicker than the production defaults (as in the service tests), so
/// the short plan's run takes well under a minute on the twin.
const FAST: &str = "[tracking]\nrest_ms = 200\naverage_frames = 100\nsettle_ms = 100\n\n\
                    [capture]\nframes = 100\nsettle_ms = 200\n";

/// A real twin + service session, recorded (see the module comment).
#[derive(Debug, Serialize, Deserialize)]
struct Fixture {
    about: String,
    /// The user the service named in its `status` reply.
    user: String,
    /// At rest at 0 mm after `nominal 0` and `zero`.
    rest: Snapshot,
    plan: PlanSpec,
    /// The service's reply to run 2's `run_start`.
    start_reply: serde_json::Value,
    /// Snapshots while run 2 went (one per new capture, then one after it ended), with seconds
    /// since `run_start` was answered.
    progress: Vec<(f64, Snapshot)>,
    /// How many `progress` entries came before `live_result` was asked.
    mid: usize,
    /// `run_result` of run 2 half-way (the captures so far, no figures).
    live_result: serde_json::Value,
    /// `run_status` after run 2 ended.
    finished_status: serde_json::Value,
    /// `run_result` of run 2 and of run 1 after both ended.
    result_2: serde_json::Value,
    result_1: serde_json::Value,
    /// `runs` after both ended.
    runs: serde_json::Value,
    /// `audit` after both ended (every operator request of the session).
    audit: serde_json::Value,
    /// The twin PLC: `table_generate` of run 2, `table_publish` of its first table, then
    /// `table_list` and `table_status`.
    generate_reply: serde_json::Value,
    publish_reply: serde_json::Value,
    tables: serde_json::Value,
    table_status: serde_json::Value,
    /// The twin's head: a pose set fitted and accepted, a second one fitted (`calibration_fit`'s
    /// reply) and left pending, then `calibration`.
    fit_reply: serde_json::Value,
    calibration: serde_json::Value,
}

fn load_fixture() -> Fixture {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(FIXTURE);
    let text = std::fs::read_to_string(&path).expect("read the console fixture");
    serde_json::from_str(&text).expect("parse the console fixture")
}

/// The buffer's text, one line per row, trailing blanks dropped.
fn text(buf: &Buffer) -> String {
    let w = buf.area.width as usize;
    let mut out = String::new();
    for row in buf.content.chunks(w) {
        let mut line = String::new();
        let mut skip = 0usize;
        for cell in row {
            // A wide glyph covers the next cell, which holds nothing to print.
            if skip > 0 {
                skip -= 1;
                continue;
            }
            let sym = cell.symbol();
            skip = ratatui::text::Span::raw(sym).width().saturating_sub(1);
            line.push_str(sym);
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out
}

fn render(app: &App, w: u16, h: u16) -> Buffer {
    let mut t = Terminal::new(TestBackend::new(w, h)).expect("test terminal");
    t.draw(|f| ui::render(f, app)).expect("draw");
    t.backend().buffer().clone()
}

fn opts(color: bool) -> AppOptions {
    AppOptions {
        socket: "/run/axiscomp/control.sock".into(),
        jog_step_mm: 0.1,
        color,
    }
}

fn key(c: KeyCode) -> KeyEvent {
    KeyEvent::new(c, KeyModifiers::NONE)
}

fn chars(s: &str) -> Vec<KeyEvent> {
    s.chars().map(|c| key(KeyCode::Char(c))).collect()
}

/// Keys that type `plan` into the Measure form from its first field, leaving the selection
/// on the first field again.
fn plan_keys(plan: &PlanSpec) -> Vec<KeyEvent> {
    let mut keys = Vec::new();
    for f in Field::ALL {
        keys.push(key(KeyCode::Enter));
        keys.extend(std::iter::repeat_n(key(KeyCode::Backspace), 16));
        keys.extend(chars(&f.get(plan)));
        keys.push(key(KeyCode::Enter));
        keys.push(key(KeyCode::Down));
    }
    keys
}

/// Answer every request in `actions` (and those the answers lead to) with `reply`; returns
/// the requests in the order they were sent.
fn answer(
    app: &mut App,
    actions: Vec<Action>,
    now: Instant,
    reply: &dyn Fn(&Request) -> serde_json::Value,
) -> Vec<Request> {
    let mut queue: VecDeque<Action> = actions.into();
    let mut sent = Vec::new();
    while let Some(a) = queue.pop_front() {
        if let Action::Send { id, request } = a {
            let v = reply(&request);
            sent.push(request);
            queue.extend(app.handle_reply(id, Ok(v), now));
        }
    }
    sent
}

/// The service's recorded replies.
fn replies(fx: &Fixture, ended: bool) -> impl Fn(&Request) -> serde_json::Value + '_ {
    move |r| match r {
        Request::RunStatus if !ended => {
            let (_, s) = &fx.progress[fx.mid - 1];
            let r = s.run.as_ref().expect("a run in the mid snapshot");
            serde_json::json!({"run_id": r.id, "state": "running", "captures": r.captures,
                "expected": r.expected, "missing": 0, "program": r.program})
        }
        Request::RunStatus => fx.finished_status.clone(),
        Request::RunResult { run_id: Some(id) } if !ended => {
            assert_eq!(Some(*id), fx.start_reply["run_id"].as_i64());
            fx.live_result.clone()
        }
        Request::RunResult { run_id: Some(id) }
            if Some(*id) == fx.result_1["run"]["id"].as_i64() =>
        {
            fx.result_1.clone()
        }
        Request::RunResult { run_id: Some(id) } => {
            assert_eq!(Some(*id), fx.result_2["run"]["id"].as_i64());
            fx.result_2.clone()
        }
        Request::Runs { .. } => fx.runs.clone(),
        Request::Audit { .. } => fx.audit.clone(),
        Request::TableList { .. } => fx.tables.clone(),
        Request::TableStatus => fx.table_status.clone(),
        Request::TablePublish { confirm: true, .. } => fx.publish_reply.clone(),
        Request::Calibration => fx.calibration.clone(),
        // The recorded session ran no hexapod calibration.
        Request::HexapodStatus => serde_json::json!({"state": "idle"}),
        other => panic!("the console sent {other:?} here"),
    }
}

/// The app at rest: connected as an operator, the rest snapshot.
fn rest_app(fx: &Fixture, t0: Instant, color: bool) -> App {
    let mut app = App::new(opts(color), t0);
    app.handle_connected(
        Identity {
            user: Some(fx.user.clone()),
            role: Some(PeerRole::Operator),
        },
        t0,
    );
    assert!(app.handle_snapshot(fx.rest.clone(), t0).is_empty());
    assert!(app.tick(t0).is_empty());
    app
}

/// The app half-way through run 2: the plan typed in, started by keys, the service's reply,
/// the recorded snapshots up to `mid`, and the Measure screen's polls answered.
fn mid_run_app(fx: &Fixture, t0: Instant, color: bool) -> (App, Instant) {
    let mut app = rest_app(fx, t0, color);
    for k in chars("4").into_iter().chain(plan_keys(&fx.plan)) {
        assert!(app.handle_key(k).is_empty());
    }
    assert_eq!(app.plan.spec, fx.plan);
    assert!(app.handle_key(key(KeyCode::Char('s'))).is_empty());
    let out = app.handle_key(key(KeyCode::Char('y')));
    let [Action::Send { id, request }] = &out[..] else {
        panic!("start sends one request: {out:?}")
    };
    assert!(matches!(request, Request::RunStart { plan, .. } if *plan == fx.plan));
    app.handle_reply(*id, Ok(fx.start_reply.clone()), t0);
    let mut last = t0;
    for (t, s) in &fx.progress[..fx.mid] {
        last = t0 + Duration::from_secs_f64(*t);
        assert!(app.handle_snapshot(s.clone(), last).is_empty());
    }
    let now = last + Duration::from_millis(500);
    let actions = app.tick(now);
    let sent = answer(&mut app, actions, now, &replies(fx, false));
    assert!(
        matches!(
            &sent[..],
            [Request::RunStatus, Request::RunResult { run_id: Some(_) }]
        ),
        "{sent:?}"
    );
    (app, now)
}

/// The app after run 2 ended: the rest of the snapshots, the end noticed and its result
/// fetched, then on the Results screen run 1 picked (↓) to compare with (b).
fn results_app(fx: &Fixture, t0: Instant, color: bool) -> App {
    let (mut app, _) = mid_run_app(fx, t0, color);
    let reply = replies(fx, true);
    let run2 = fx.start_reply["run_id"].as_i64();
    let mut now = t0;
    for (t, s) in &fx.progress[fx.mid..] {
        now = t0 + Duration::from_secs_f64(*t);
        let actions = app.handle_snapshot(s.clone(), now);
        let sent = answer(&mut app, actions, now, &reply);
        if s.run.is_none() {
            // The run ended: the console asked how, then for its result.
            assert_eq!(sent.first(), Some(&Request::RunStatus), "{sent:?}");
            assert!(
                sent.contains(&Request::RunResult { run_id: run2 }),
                "{sent:?}"
            );
        }
    }
    assert_eq!(app.run.as_ref().map(|r| r.state.as_str()), Some("finished"));
    assert_eq!(app.results.shown.as_ref().map(|r| r.run.id), run2);
    // The Results screen asks for the run list.
    let actions = app.handle_key(key(KeyCode::Char('5')));
    let sent = answer(&mut app, actions, now, &reply);
    assert_eq!(sent, [Request::Runs { limit: None }]);
    assert!(app.results.runs.len() >= 2, "{:?}", app.results.runs);
    assert!(app.handle_key(key(KeyCode::Down)).is_empty());
    let actions = app.handle_key(key(KeyCode::Char('b')));
    let sent = answer(&mut app, actions, now, &reply);
    assert_eq!(sent.len(), 1, "{sent:?}");
    assert_eq!(
        app.results.before.as_ref().map(|r| r.run.id),
        fx.result_1["run"]["id"].as_i64()
    );
    app
}

const SIZES: [(u16, u16); 2] = [(80, 24), (160, 48)];

fn snapshot_screens(app: &mut App, screens: &[Screen]) {
    for &s in screens {
        app.screen = s;
        for (w, h) in SIZES {
            let name = format!("{}_{w}x{h}", s.title().to_lowercase());
            insta::assert_snapshot!(name, text(&render(app, w, h)));
        }
    }
}

#[test]
fn every_screen_renders_from_a_twin_run_at_80x24_and_160x48() {
    let fx = load_fixture();
    let t0 = axiscomp::util::clock::now();
    let mut rest = rest_app(&fx, t0, true);
    snapshot_screens(&mut rest, &[Screen::Live, Screen::Align]);
    let (mut mid, _) = mid_run_app(&fx, t0, true);
    snapshot_screens(&mut mid, &[Screen::Measure]);
    let mut done = results_app(&fx, t0, true);
    snapshot_screens(&mut done, &[Screen::Results]);
    // Events asks for the audit log when it shows.
    let now = done.now;
    let actions = done.handle_key(key(KeyCode::Char('7')));
    let sent = answer(&mut done, actions, now, &replies(&fx, true));
    assert_eq!(sent, [Request::Audit { limit: Some(50) }]);
    snapshot_screens(&mut done, &[Screen::Events]);
}

/// An axis's trend as the service's `trend` computes it (`service::trends`): 14 weekly runs
/// of E, steady at about 5 µm for 8 and then wearing 0.25 µm a week, with a tolerance of 8 µm;
/// B steady; everything charted by the library, not here.
fn trend_reply() -> serde_json::Value {
    use axiscomp::report::settings::{AcceptanceSettings, Tolerance};
    use axiscomp::service::trends::{FigureHistory, Judged};
    let t0 = 1_790_000_000_000_000_i64;
    let week = 7 * 86_400_000_000_i64;
    let scatter = [
        0.04, -0.03, 0.05, -0.06, 0.01, 0.03, -0.02, -0.01, 0.02, -0.04, 0.03, 0.0, -0.02, 0.01,
    ];
    let history = |dof: &str, name: &str, f: &dyn Fn(usize) -> f64| FigureHistory {
        dof: dof.into(),
        name: name.into(),
        unit: "µm".into(),
        points: (0..14)
            .map(|i| (i as i64 + 3, t0 + i as i64 * week, f(i) + scatter[i]))
            .collect(),
    };
    let e = history("dy", "E (systematic)", &|i| {
        5.0 + 0.25 * (i as f64 - 7.0).max(0.0)
    });
    let b = history("dy", "B (reversal)", &|_| 1.2);
    let acceptance = AcceptanceSettings {
        tolerances: vec![Tolerance {
            figure: "E",
            limit: 8.0,
            unit: "µm",
            key: "acceptance.e_um",
        }],
    };
    let settings = axiscomp::trend::Settings::default();
    let figures: Vec<serde_json::Value> = [b, e]
        .into_iter()
        .map(|h| Judged::of(h, t0, &acceptance, &settings).to_json(t0))
        .collect();
    serde_json::json!({"axis": "X", "runs": (3..17).collect::<Vec<i64>>(),
        "compensation": "positioning X sequence 4 CRC 0x1A2B3C4D", "runs_under_other_tables": 2,
        "figures": figures})
}

#[test]
fn the_trends_view_shows_each_figure_against_its_limits_at_80x24_and_160x48() {
    let fx = load_fixture();
    let t0 = axiscomp::util::clock::now();
    let mut app = results_app(&fx, t0, true);
    let trend = trend_reply();
    let reply = |r: &Request| match r {
        Request::Trend { axis: None } => trend.clone(),
        other => panic!("the console sent {other:?} here"),
    };
    let actions = app.handle_key(key(KeyCode::Char('t')));
    let sent = answer(&mut app, actions, t0, &reply);
    assert_eq!(sent, [Request::Trend { axis: None }]);
    // The figure in alarm is highlighted first: E, wearing since run 11.
    let f = app.trends.figure().expect("a figure");
    assert!(f.name.starts_with('E'), "{}", f.name);
    assert!(f.alarm_run.is_some(), "{f:?}");
    for (w, h) in SIZES {
        let screen = text(&render(&app, w, h));
        assert!(screen.contains("DRIFT since run"), "{screen}");
        assert!(screen.contains("within a table's reach"), "{screen}");
        insta::assert_snapshot!(format!("trends_{w}x{h}"), screen);
    }
    // ↑ picks B; t goes back to the runs.
    assert!(app.handle_key(key(KeyCode::Up)).is_empty());
    assert!(app.trends.figure().is_some_and(|f| f.name.starts_with('B')));
    assert!(app.handle_key(key(KeyCode::Char('t'))).is_empty());
    assert!(!app.trends.shown);
    assert!(text(&render(&app, 80, 24)).contains("Runs (Enter, b, t)"));
}

/// The Calibrate screen as it shows itself: the service's `calibration` (one in use, one
/// pending from the twin's head).
fn calibrate_app(fx: &Fixture, t0: Instant, color: bool) -> App {
    let mut app = rest_app(fx, t0, color);
    let actions = app.handle_key(key(KeyCode::Char('3')));
    let sent = answer(&mut app, actions, t0, &replies(fx, true));
    assert_eq!(sent, [Request::Calibration, Request::HexapodStatus]);
    app
}

/// The Publish screen after run 2: the tables and the PLC's status asked for as it shows,
/// then the first table published by keys (p, the axis typed, Enter) with the recorded reply.
fn publish_app(fx: &Fixture, t0: Instant, color: bool) -> App {
    let mut app = results_app(fx, t0, color);
    let now = app.now;
    let reply = replies(fx, true);
    let actions = app.handle_key(key(KeyCode::Char('6')));
    let sent = answer(&mut app, actions, now, &reply);
    assert_eq!(
        sent,
        [Request::TableList { limit: None }, Request::TableStatus]
    );
    let first = fx.publish_reply["table_id"]
        .as_i64()
        .expect("published table");
    while app.publish.selected_table().map(|t| t.id) != Some(first) {
        app.handle_key(key(KeyCode::Down));
    }
    assert!(app.handle_key(key(KeyCode::Char('p'))).is_empty());
    let axis = app
        .publish
        .selected_table()
        .map(|t| t.axis.clone())
        .expect("table");
    for k in chars(&axis) {
        assert!(app.handle_key(k).is_empty());
    }
    let actions = app.handle_key(key(KeyCode::Enter));
    let sent = answer(&mut app, actions, now, &reply);
    assert_eq!(
        sent,
        [
            Request::TablePublish {
                table_id: first,
                confirm: true
            },
            Request::TableList { limit: None },
            Request::TableStatus
        ]
    );
    app
}

#[test]
fn calibrate_and_publish_render_from_the_twin_session() {
    let fx = load_fixture();
    let t0 = axiscomp::util::clock::now();
    let mut cal = calibrate_app(&fx, t0, true);
    snapshot_screens(&mut cal, &[Screen::Calibrate]);
    let mut publ = publish_app(&fx, t0, true);
    snapshot_screens(&mut publ, &[Screen::Publish]);
    // The numbers are the service's.
    let mut plain = calibrate_app(&fx, t0, false);
    plain.screen = Screen::Calibrate;
    let t = text(&render(&plain, 160, 48));
    let pending = &fx.calibration["pending"];
    let cond = pending["condition_number"]
        .as_f64()
        .expect("condition number");
    assert!(t.contains(&format!("{cond:.3e}")), "{t}");
    for k in 0..6 {
        let m = pending["model_residual_um"][k]
            .as_f64()
            .expect("model residual");
        assert!(
            t.contains(&format!("{m:.2}")),
            "model residual {k} = {m}:\n{t}"
        );
    }
    assert!(t.contains("stored calibration"), "{t}");
    let publ = publish_app(&fx, t0, false);
    let t = text(&render(&publ, 160, 48));
    let seq = fx.publish_reply["sequence"].as_u64().expect("sequence");
    assert!(t.contains(&format!("committed as sequence {seq}")), "{t}");
    assert!(t.contains("matches table"), "{t}");
    assert!(t.contains("equals table"), "the per-point diff:\n{t}");
}

#[test]
fn the_screens_show_the_twin_data_they_are_given() {
    // Independent of the snapshots: the numbers on screen are the fixture's.
    let fx = load_fixture();
    let t0 = axiscomp::util::clock::now();
    let rest = rest_app(&fx, t0, false);
    let live = text(&render(&rest, 160, 48));
    let l = fx.rest.live.as_ref().expect("live errors at rest");
    for (k, v) in l.errors.iter().enumerate() {
        let dec = if k < 3 { 3 } else { 2 };
        assert!(
            live.contains(&format!("{v:+.dec$}")),
            "error {k} = {v}:\n{live}"
        );
    }
    let p = fx.rest.psd.as_ref().expect("a frame at rest");
    for sum in p.sums_v {
        assert!(live.contains(&format!("{sum:.2} V")), "SUM {sum}:\n{live}");
    }
    // Align names the follower's error map in use, and says when there is none.
    let mut align = rest_app(&fx, t0, false);
    align.screen = Screen::Align;
    let t = text(&render(&align, 80, 24));
    assert!(t.contains("no follower map (follower import)"), "{t}");
    let mut snap = fx.rest.clone();
    let src = axiscomp::follower::Source::Certificate;
    snap.tracking.follower_map = Some(axiscomp::service::api::FollowerMapView {
        id: 3,
        name: "stage-7".into(),
        source: "certificate".into(),
        created: "2026-11-20T08:15:00Z".into(),
        sources: axiscomp::follower::Sources {
            long: src,
            periodic: src,
            reversal: src,
            vertical: src,
        },
    });
    align.handle_snapshot(snap, t0);
    let t = text(&render(&align, 80, 24));
    // (wrapped at 80 columns after the date)
    assert!(t.contains("map stage-7, 2026-11-20,"), "{t}");
    assert!(t.contains("certificate"), "{t}");
    let mut done = results_app(&fx, t0, false);
    done.screen = Screen::Results;
    let res = text(&render(&done, 160, 48));
    let r2: axiscomp::service::results::RunResult =
        serde_json::from_value(fx.result_2.clone()).expect("result 2");
    let dy = &r2.dofs[1];
    assert_eq!(dy.name, "dy");
    let repeat = dy
        .figures
        .iter()
        .find(|f| f.name.starts_with("R "))
        .expect("R in the figures");
    assert!(res.contains(&format!("{:.2}", repeat.value)), "{res}");
    assert!(res.contains("before: run"), "{res}");
    // ← → walk the errors on the narrow layout.
    assert_eq!(done.results.dof, 1, "positioning first");
    for (k, name) in ["dz", "ex", "ey", "ez", "dx", "dy"].iter().enumerate() {
        done.handle_key(key(KeyCode::Right));
        assert_eq!(done.results.dof, (k + 2) % 6);
        let t = text(&render(&done, 80, 24));
        assert!(t.contains(&format!("{name} ")), "{name}:\n{t}");
    }
}

#[test]
fn overlays_read_only_and_no_service_render() {
    let fx = load_fixture();
    let t0 = axiscomp::util::clock::now();
    // Help on the Measure screen.
    let (mut app, now) = mid_run_app(&fx, t0, true);
    app.handle_key(key(KeyCode::Char('?')));
    insta::assert_snapshot!("help_measure_80x24", text(&render(&app, 80, 24)));
    // Confirming an abort.
    app.handle_key(key(KeyCode::Esc));
    assert!(app.handle_key(key(KeyCode::Char('a'))).is_empty());
    insta::assert_snapshot!("confirm_abort_80x24", text(&render(&app, 80, 24)));
    let out = app.handle_key(key(KeyCode::Char('y')));
    assert!(
        matches!(
            &out[..],
            [Action::Send {
                request: Request::RunAbort,
                ..
            }]
        ),
        "{out:?}"
    );
    let _ = now;
    // A confirmation whose text wraps over many rows still shows its y / n line (the
    // override of an implausible calibration, at 80×24).
    let (mut app, _) = mid_run_app(&fx, t0, true);
    app.calibrate.pending = Some(axiscomp::service::calibration::Summary {
        source: "/var/lib/axiscomp/poses/other-head.csv".into(),
        concerns: vec![
            "at the carriage's current position it reads dx -166.6 µm, dy -321.8 µm, ex +209.9 arcsec, ey -1929.8 arcsec, ez +107.9 arcsec (plausible: within ±100 µm and ±100 arcsec): the pose set was probably made with another head".into(),
            "the model fit's residual RMS is X3 12.00 µm (plausible: up to 5.0 µm, a few times a PSD's noise): the fit does not describe its poses".into(),
        ],
        ..Default::default()
    });
    app.handle_key(key(KeyCode::Char('3')));
    app.handle_key(key(KeyCode::Char('A')));
    let screen = text(&render(&app, 80, 24));
    assert!(screen.contains("OVERRIDE"), "{screen}");
    assert!(screen.contains(" y  yes     n  no"), "{screen}");
    app.handle_key(key(KeyCode::Char('n')));
    // A viewer: read-only, operator keys refused with a message.
    let mut viewer = App::new(opts(true), t0);
    viewer.handle_connected(
        Identity {
            user: Some("nobody".into()),
            role: Some(PeerRole::Viewer),
        },
        t0,
    );
    viewer.handle_snapshot(fx.rest.clone(), t0);
    viewer.handle_key(key(KeyCode::Char('2')));
    assert!(viewer.handle_key(key(KeyCode::Char('z'))).is_empty());
    insta::assert_snapshot!("align_viewer_80x24", text(&render(&viewer, 80, 24)));
    // The service went away: last known values, marked.
    let mut gone = rest_app(&fx, t0, true);
    gone.handle_down(
        &ClientError::Connect {
            path: "/run/axiscomp/control.sock".into(),
            reason: "Connection refused (os error 111)".into(),
        },
        Duration::from_millis(800),
        t0 + Duration::from_secs(5),
    );
    gone.tick(t0 + Duration::from_secs(5));
    insta::assert_snapshot!("live_no_service_80x24", text(&render(&gone, 80, 24)));
    // Never connected.
    let never = App::new(opts(true), t0);
    insta::assert_snapshot!("live_connecting_80x24", text(&render(&never, 80, 24)));
}

#[test]
fn no_color_draws_without_colours() {
    use ratatui::style::Color;
    let fx = load_fixture();
    let t0 = axiscomp::util::clock::now();
    for color in [true, false] {
        let mut app = results_app(&fx, t0, color);
        let mut coloured = 0usize;
        for s in Screen::ALL {
            app.screen = s;
            let buf = render(&app, 160, 48);
            coloured += buf
                .content
                .iter()
                .filter(|c| c.fg != Color::Reset || c.bg != Color::Reset)
                .count();
        }
        if color {
            assert!(coloured > 100, "colours drawn: {coloured}");
        } else {
            assert_eq!(coloured, 0, "NO_COLOR: no cell has a colour");
        }
    }
}

// ---------- against a live service and twin ----------

/// The real console loop on a `TestBackend`, driven in slices so the test can look between
/// them.
struct Console {
    term: Terminal<TestBackend>,
    app: App,
    client: Client,
}

impl Console {
    fn start(socket: &Path, w: u16, h: u16) -> Console {
        Console {
            term: Terminal::new(TestBackend::new(w, h)).expect("terminal"),
            app: App::new(
                AppOptions {
                    socket: socket.display().to_string(),
                    jog_step_mm: 0.1,
                    color: true,
                },
                axiscomp::util::clock::now(),
            ),
            client: Client::spawn(ClientOptions::new(socket.to_path_buf())),
        }
    }

    /// Run the loop with `keys` (then no more keys) for `slice`.
    async fn run(&mut self, keys: Vec<KeyEvent>, slice: Duration) {
        let keys = futures_util::stream::iter(keys.into_iter().map(|k| Ok(Event::Key(k))))
            .chain(futures_util::stream::pending());
        let r = tokio::time::timeout(
            slice,
            drive(
                &mut self.term,
                &mut self.app,
                keys,
                &mut self.client,
                Duration::from_millis(100),
            ),
        )
        .await;
        if let Ok(r) = r {
            r.expect("the console loop");
        }
    }

    async fn keys(&mut self, keys: Vec<KeyEvent>) {
        self.run(keys, Duration::from_millis(400)).await;
    }

    fn screen(&self) -> String {
        text(self.term.backend().buffer())
    }

    async fn until(&mut self, secs: u64, what: &str, pred: impl Fn(&App) -> bool) {
        let end = axiscomp::util::clock::now() + Duration::from_secs(secs);
        while !pred(&self.app) {
            assert!(
                axiscomp::util::clock::now() < end,
                "{what}: not within {secs} s; the screen:\n{}",
                self.screen()
            );
            self.run(Vec::new(), Duration::from_millis(200)).await;
        }
    }
}

/// Wait until the snapshots have shown the tracking referenced and at rest for a second.
async fn settle(c: &mut Console) {
    let at_rest = |a: &App| {
        a.snapshot
            .as_ref()
            .is_some_and(|s| s.run.is_none() && s.tracking.valid && s.tracking.at_rest)
    };
    let end = axiscomp::util::clock::now() + Duration::from_secs(30);
    let mut since: Option<Instant> = None;
    loop {
        c.run(Vec::new(), Duration::from_millis(200)).await;
        since = if at_rest(&c.app) {
            since.or(Some(axiscomp::util::clock::now()))
        } else {
            None
        };
        if since.is_some_and(|t| axiscomp::util::clock::since(t) >= Duration::from_secs(1)) {
            return;
        }
        assert!(
            axiscomp::util::clock::now() < end,
            "not at rest within 30 s:\n{}",
            c.screen()
        );
    }
}

#[tokio::test(start_paused = true)]
async fn measure_workflow_by_keys_against_the_twin() {
    let rig = ServiceRig::start(RigOptions {
        service_toml: FAST.into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    let mut c = Console::start(&rig.socket, 80, 24);
    c.until(10, "connected with a snapshot", |a| {
        a.link == LinkState::Up && a.snapshot.is_some()
    })
    .await;
    assert_eq!(
        c.app.access,
        Access::Operator,
        "the status reply names the role"
    );
    c.run(Vec::new(), Duration::from_millis(300)).await;
    assert!(c.screen().contains("Six errors"), "{}", c.screen());
    // Plan: typed into the form on the Measure screen.
    let plan = short_plan();
    let mut keys = chars("4");
    keys.extend(plan_keys(&plan));
    c.keys(keys).await;
    assert_eq!(c.app.plan.spec, plan);
    assert!(c.screen().contains("✓ 20 captures"), "{}", c.screen());
    // Start before the beam is aligned: the service's pre-run check refuses, in words.
    c.keys(chars("s")).await;
    assert!(c.screen().contains("Start the run?"), "{}", c.screen());
    c.keys(chars("y")).await;
    c.run(Vec::new(), Duration::from_millis(500)).await;
    assert!(c.app.run.is_none(), "started without an alignment");
    assert!(c.screen().contains("no beam alignment"), "{}", c.screen());
    // Aligned over the plan's travel (the Align screen's keys are console.sh's), it starts.
    let travel = axiscomp::run::Plan::new(plan.clone())
        .expect("plan")
        .travel_mm();
    crate::helpers::align_service(&rig.socket, &rig.twin, travel).await;
    c.keys(chars("s")).await;
    assert!(c.screen().contains("Start the run?"), "{}", c.screen());
    c.keys(chars("y")).await;
    c.until(10, "the run started", |a| a.run.is_some()).await;
    let run_id = c.app.run.as_ref().map(|r| r.run_id).expect("run id");
    // Progress: captures come in, the ETA and the live plot appear.
    c.until(90, "four captures and their live plot", |a| {
        a.run.as_ref().is_some_and(|r| {
            r.captures >= 4 && r.live.as_ref().is_some_and(|l| l.run.captures >= 4)
        })
    })
    .await;
    c.run(Vec::new(), Duration::from_millis(300)).await;
    let r = c.app.run.clone().expect("run");
    assert_eq!(r.expected, Some(20));
    assert!(r.eta().is_some(), "{r:?}");
    let s = c.screen();
    assert!(s.contains(&format!("run {run_id} running")), "{s}");
    assert!(s.contains("ETA"), "{s}");
    assert!(s.contains("run 1  ↑ ■■■■"), "{s}");
    assert!(s.contains("dy positioning (µm)"), "the live plot:\n{s}");
    // Results: the run ends, the console fetches its evaluation by itself.
    c.until(120, "the run finished", |a| {
        a.run.as_ref().is_some_and(|r| r.state == "finished")
    })
    .await;
    c.until(10, "its result", |a| {
        a.results.shown.as_ref().is_some_and(|r| r.run.id == run_id)
    })
    .await;
    c.keys(chars("5")).await;
    c.until(10, "the run list", |a| a.results.listed).await;
    c.run(Vec::new(), Duration::from_millis(300)).await;
    let s = c.screen();
    let shown = c.app.results.shown.clone().expect("result");
    assert_eq!(shown.run.captures, 20);
    assert_eq!(shown.incomplete, None, "a finished run has figures");
    assert!(
        s.contains(&format!("run {run_id} X finished, 20 captures")),
        "{s}"
    );
    assert!(s.contains("dy positioning (µm)"), "{s}");
    assert!(s.contains("A (accuracy)"), "{s}");
    // The wide layout shows all six charts.
    let mut wide = c.app.clone();
    wide.screen = Screen::Results;
    let t = text(&render(&wide, 160, 48));
    for d in [
        "dx horizontal",
        "dy positioning",
        "dz vertical",
        "ex pitch",
        "ey roll",
        "ez yaw",
    ] {
        assert!(t.contains(d), "{d}:\n{t}");
    }
    // Events: the audit log names the run's start, by whom.
    c.keys(chars("7")).await;
    c.until(10, "the audit log", |a| {
        a.audit
            .as_ref()
            .is_some_and(|v| v.iter().any(|e| e.action == "run_start"))
    })
    .await;
    c.run(Vec::new(), Duration::from_millis(300)).await;
    let s = c.screen();
    assert!(
        s.contains("run_start X 0.0–8.0 mm, 5 targets, 2 runs"),
        "{s}"
    );
    // Abort: a second run, started and aborted by keys. Started, as an operator would, once
    // the Live screen says the carriage and the follower are at rest: a run started during a
    // handover moves the carriage away under it and fails ("PSD2 lost the spot").
    settle(&mut c).await;
    c.keys(chars("4")).await;
    c.keys(chars("s")).await;
    c.keys(chars("y")).await;
    c.until(20, "the second run started", |a| {
        a.run
            .as_ref()
            .is_some_and(|r| r.run_id > run_id && r.running())
    })
    .await;
    c.keys(chars("a")).await;
    assert!(c.screen().contains("Abort the run?"), "{}", c.screen());
    c.keys(chars("y")).await;
    c.until(20, "the run aborted", |a| {
        a.run.as_ref().is_some_and(|r| r.state == "aborted") && !a.run_active()
    })
    .await;
    // q quits at once when no run is active.
    let mut quit = false;
    within_s(5, "quit", async {
        let keys = futures_util::stream::iter([Ok(Event::Key(key(KeyCode::Char('q'))))])
            .chain(futures_util::stream::pending());
        drive(
            &mut c.term,
            &mut c.app,
            keys,
            &mut c.client,
            Duration::from_millis(100),
        )
        .await
        .expect("loop");
        quit = true;
    })
    .await;
    assert!(quit);
    rig.stop().await;
}

/// Record `fixtures/console_twin.json` from a real twin + service session:
/// `cargo test --test it console::capture_console_fixture -- --ignored`, then review the
/// snapshots that change (`INSTA_UPDATE=always` or `cargo insta review`).
#[tokio::test(start_paused = true)]
#[ignore = "writes the fixture; run by hand when the snapshot or the screens change"]
async fn capture_console_fixture() {
    let rig = ServiceRig::start(RigOptions {
        service_toml: FAST.into(),
        twin_cnc: true,
        twin_plc: true,
        ..RigOptions::default()
    })
    .await;
    rig.request(Request::Nominal { mm: Some(0.0) })
        .await
        .expect("nominal");
    rig.request(Request::Zero).await.expect("zero");
    rig.twin.plant.set_blocked(2, true);
    rig.wait_for(10, "the beam-blocked alarm", |s| {
        s.alarms
            .iter()
            .any(|a| a.code == "beam-blocked" && a.active)
    })
    .await;
    rig.twin.plant.set_blocked(2, false);
    tokio::time::sleep(Duration::from_millis(300)).await;
    rig.wait_for(10, "a full live window again", |s| {
        s.live.as_ref().is_some_and(|l| l.frames >= 100) && s.tracking.at_rest
    })
    .await;
    let user = axiscomp::service::peer::user_name(unsafe { libc::geteuid() })
        .unwrap_or_else(|| "root".into());
    let rest = rig.snapshot().await;
    let plan = short_plan();
    let travel = axiscomp::run::Plan::new(plan.clone())
        .expect("plan")
        .travel_mm();
    crate::helpers::align_service(&rig.socket, &rig.twin, travel).await;
    let start = || Request::RunStart {
        plan: plan.clone(),
        dialect: None,
        notes: None,
    };
    // Run 1, to the end: the "before" of the comparison.
    let first = rig.request(start()).await.expect("run_start 1");
    let t1 = axiscomp::util::clock::now();
    loop {
        let status = rig.request(Request::RunStatus).await.expect("status");
        match status["state"].as_str() {
            Some("running") => {}
            Some("finished") => break,
            _ => panic!("run 1 ended so: {status}"),
        }
        assert!(
            axiscomp::util::clock::since(t1) < Duration::from_secs(180),
            "run 1 stalls"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // The snapshot catches up (it shows no run), and the last handover is over: a run started
    // during one fails ("PSD2 lost the spot").
    rig.wait_for(5, "no run in the snapshot", |s| s.run.is_none())
        .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    rig.wait_for(30, "at rest", |s| s.tracking.valid && s.tracking.at_rest)
        .await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    rig.wait_for(30, "still at rest", |s| {
        s.tracking.valid && s.tracking.at_rest
    })
    .await;
    // Run 2, recorded.
    let start_reply = rig.request(start()).await.expect("run_start 2");
    let t0 = axiscomp::util::clock::now();
    let mut progress: Vec<(f64, Snapshot)> = Vec::new();
    let mut last = usize::MAX;
    let mut live = None;
    loop {
        assert!(
            axiscomp::util::clock::since(t0) < Duration::from_secs(180),
            "run 2 stalls"
        );
        let s = rig.snapshot().await;
        let t = axiscomp::util::clock::since(t0).as_secs_f64();
        match &s.run {
            // Before the first snapshot of run 2 no run shows either.
            None if progress.is_empty() => {}
            None => {
                progress.push((t, s));
                break;
            }
            Some(r) if r.captures != last => {
                last = r.captures;
                progress.push((t, s.clone()));
                if live.is_none() && r.captures >= r.expected / 2 {
                    let v = rig
                        .request(Request::RunResult { run_id: Some(r.id) })
                        .await
                        .expect("run_result half-way");
                    live = Some((progress.len(), v));
                }
            }
            Some(_) => {}
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (mid, live_result) = live.expect("a half-way result");
    let finished_status = rig.request(Request::RunStatus).await.expect("status");
    assert_eq!(finished_status["state"], "finished", "{finished_status}");
    let result = |id: &serde_json::Value| Request::RunResult {
        run_id: id.as_i64(),
    };
    let result_2 = rig
        .request(result(&start_reply["run_id"]))
        .await
        .expect("result 2");
    let result_1 = rig
        .request(result(&first["run_id"]))
        .await
        .expect("result 1");
    let runs = rig
        .request(Request::Runs { limit: None })
        .await
        .expect("runs");
    // Tables from run 2, the first published into the twin PLC.
    let generate_reply = rig
        .request(Request::TableGenerate {
            run_id: start_reply["run_id"].as_i64().expect("run 2"),
            residual_only: false,
        })
        .await
        .expect("table_generate");
    let publish_reply = rig
        .request(Request::TablePublish {
            table_id: generate_reply["tables"][0]["id"].as_i64().expect("a table"),
            confirm: true,
        })
        .await
        .expect("table_publish");
    assert_eq!(publish_reply["result"], "committed", "{publish_reply}");
    let tables = rig
        .request(Request::TableList { limit: None })
        .await
        .expect("table_list");
    let table_status = rig.request(Request::TableStatus).await.expect("status");
    // The twin's head: one pose set fitted and accepted, a second fitted and left pending.
    let poses_dir =
        std::env::temp_dir().join(format!("axiscomp-console-fx-{}", std::process::id()));
    let mut fit_reply = serde_json::Value::Null;
    for (k, seed) in [(1, 77u64), (2, 78)] {
        let path = twin_pose_set(&RigOptions::default().plant, &poses_dir, k, seed);
        fit_reply = rig
            .request(Request::CalibrationFit {
                poses: path.display().to_string(),
            })
            .await
            .expect("calibration_fit");
        if k == 1 {
            rig.request(Request::CalibrationAccept { force: false })
                .await
                .expect("calibration_accept");
        }
    }
    let calibration = rig
        .request(Request::Calibration)
        .await
        .expect("calibration");
    let moved_poses = |v: serde_json::Value| -> serde_json::Value {
        let t = v
            .to_string()
            .replace(&poses_dir.display().to_string(), "/var/lib/axiscomp/poses");
        serde_json::from_str(&t).expect("json")
    };
    let _ = std::fs::remove_dir_all(&poses_dir);
    let audit = rig
        .request(Request::Audit { limit: None })
        .await
        .expect("audit");
    // Redaction: shift every timestamp so the rest snapshot is at 2026-01-01 08:00:00 UTC.
    let shift = 1_767_254_400_000_000 - rest.unix_us;
    let redact = |mut s: Snapshot| {
        s.unix_us += shift;
        for a in &mut s.alarms {
            a.since_unix_us += shift;
        }
        if let Some(r) = &mut s.run {
            r.program = moved(&r.program);
        }
        s
    };
    let redact_value = |mut v: serde_json::Value| {
        shift_json(&mut v, shift);
        v
    };
    let mut start_reply = start_reply;
    if let Some(p) = start_reply["program"].as_str() {
        start_reply["program"] = serde_json::Value::String(moved(p));
    }
    let fx = Fixture {
        about: "twin + service on loopback (tests/it/console.rs capture_console_fixture): \
                timestamps shifted so the rest snapshot is at 2026-01-01 08:00:00 UTC, program \
                paths moved to /var/lib/axiscomp; everything else as the service sent it"
            .into(),
        user,
        rest: redact(rest),
        plan,
        start_reply,
        progress: progress
            .into_iter()
            .map(|(t, s)| ((t * 1000.0).round() / 1000.0, redact(s)))
            .collect(),
        mid,
        live_result: redact_value(live_result),
        finished_status: redact_value(finished_status),
        result_2: redact_value(result_2),
        result_1: redact_value(result_1),
        runs: redact_value(runs),
        audit: moved_poses(redact_value(audit)),
        generate_reply: redact_value(generate_reply),
        publish_reply: redact_value(publish_reply),
        tables: redact_value(tables),
        table_status: redact_value(table_status),
        fit_reply: moved_poses(redact_value(fit_reply)),
        calibration: moved_poses(redact_value(calibration)),
    };
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(FIXTURE);
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&fx).expect("serialise") + "\n",
    )
    .expect("write the fixture");
    eprintln!("wrote {}", path.display());
    rig.stop().await;
}

/// A pose set of the rig's twin head (as a hexapod would record it), written to `dir`.
fn twin_pose_set(
    plant: &axiscomp::sim::plant::PlantSpec,
    dir: &Path,
    k: usize,
    seed: u64,
) -> std::path::PathBuf {
    use axiscomp::calibrate::write_pose_csv;
    use axiscomp::optics::Layout;
    use axiscomp::sim::plant::Plant;
    use axiscomp::sim::{Hexapod, PoseWindow, Rng};
    use axiscomp::util::progress::Progress;
    let layout = Layout::reference();
    let head = Plant::draw_head(&layout, plant).expect("the twin's head");
    let rng = Rng::new(seed);
    let poses = PoseWindow::default().draw(120, &mut rng.fork(1));
    let (samples, _) =
        Hexapod::default().acquire(&head, &poses, &mut rng.fork(2), &mut Progress::hidden());
    std::fs::create_dir_all(dir).expect("pose dir");
    let path = dir.join(format!("poses-{k}.csv"));
    std::fs::write(&path, write_pose_csv(&samples, &[])).expect("pose file");
    path
}

/// A program path in the test's state directory, as if in the production one.
fn moved(p: &str) -> String {
    match p.split_once("/state/") {
        Some((_, rest)) => format!("/var/lib/axiscomp/{rest}"),
        None => p.to_string(),
    }
}

/// Shift every `*_us` timestamp in a reply by `shift`.
fn shift_json(v: &mut serde_json::Value, shift: i64) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, x) in m.iter_mut() {
                if k.ends_with("_us")
                    && let Some(t) = x.as_i64()
                {
                    *x = serde_json::Value::from(t + shift);
                } else {
                    shift_json(x, shift);
                }
            }
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(|x| shift_json(x, shift)),
        _ => {}
    }
}

/// The Calibrate screen drives a hexapod calibration through the service, by keys, against
/// the twin's PI controller: h and the default plan's size typed as a plan (empty: 200
/// poses; here a 40-pose plan file), progress with pose i of N, machine time and time left;
/// a controller error mid-plan stops it with the controller's code and text on the screen;
/// u resumes at the next pose; the fit's hold-out against the Cramér–Rao bound shows and the
/// calibration waits for accept, which puts it in use.
#[tokio::test(start_paused = true)]
async fn calibrate_screen_runs_the_hexapod_through_the_service() {
    use axiscomp::hexapod::plan::{PlanSpec, PosePlan};
    use axiscomp::sim::hexapod_servers::{HexapodFault, gcs_error_text};
    let dir = crate::helpers::TempDir::new("console-hexapod");
    let out = dir.path("run");
    let (rig, servers) = crate::helpers::hexapod_rig(
        RigOptions {
            service_toml: FAST.into(),
            ..RigOptions::default()
        },
        "settle_ms = 20\nframes = 20\nstable_um = 5.0\n",
    )
    .await;
    let plan = PosePlan::generate(&PlanSpec {
        poses: 40,
        ..PlanSpec::default()
    });
    let plan_file = dir.write("plan.csv", &plan.to_csv());
    let mut c = Console::start(&rig.socket, 160, 48);
    c.until(10, "connected", |a| {
        a.link == LinkState::Up && a.snapshot.is_some()
    })
    .await;
    c.keys(chars("3")).await;
    c.until(10, "the hexapod status", |a| a.calibrate.hexapod.is_some())
        .await;
    assert!(
        c.screen().contains("No run: h calibrates"),
        "{}",
        c.screen()
    );
    // h asks for the plan, Enter asks to confirm, y starts.
    let mut keys = chars("h");
    keys.extend(chars(&plan_file.display().to_string()));
    keys.push(key(KeyCode::Enter));
    c.keys(keys).await;
    assert!(
        c.screen().contains("Start the hexapod calibration?"),
        "{}",
        c.screen()
    );
    c.keys(chars("y")).await;
    c.until(60, "ten poses", |a| {
        a.calibrate.hexapod.as_ref().is_some_and(|h| h.done >= 10)
    })
    .await;
    let s = c.screen();
    assert!(s.contains("of 40 ("), "{s}");
    assert!(s.contains("machine time"), "{s}");
    assert!(s.contains("remaining ~"), "{s}");
    let out_dir = c.app.calibrate.hexapod.clone().expect("view").out;
    // A controller error on a coming move: the run stops with the controller's words.
    servers.hexapod.inject(HexapodFault::Error(10));
    c.until(30, "the run failed", |a| {
        a.calibrate
            .hexapod
            .as_ref()
            .is_some_and(|h| h.state == "failed")
    })
    .await;
    c.run(Vec::new(), Duration::from_millis(300)).await;
    let text10 = gcs_error_text(10);
    let s = c.screen();
    assert!(s.contains(&format!("PI C-887 error 10: {text10}")), "{s}");
    assert!(s.contains("u resume"), "{s}");
    let stored = c
        .app
        .calibrate
        .hexapod
        .as_ref()
        .map(|h| h.done)
        .unwrap_or(0);
    assert!((10..40).contains(&stored), "{stored}");
    // u resumes at the next pose, in the same run directory.
    c.keys(chars("u")).await;
    c.until(120, "the fit", |a| {
        a.calibrate
            .hexapod
            .as_ref()
            .is_some_and(|h| h.state == "done")
    })
    .await;
    let h = c.app.calibrate.hexapod.clone().expect("view");
    assert_eq!(h.out, out_dir);
    assert_eq!(h.resumed_from, stored, "{h:?}");
    let run_csv =
        std::fs::read_to_string(std::path::Path::new(&out_dir).join("run.csv")).expect("run.csv");
    let idx: Vec<usize> = run_csv
        .lines()
        .filter(|l| l.starts_with(|ch: char| ch.is_ascii_digit()))
        .filter_map(|l| l.split(',').next()?.parse().ok())
        .collect();
    assert_eq!(idx, (1..=40).collect::<Vec<_>>(), "every pose stored once");
    let ratio = h.ratio.expect("ratio");
    assert!(ratio.iter().all(|r| *r > 0.5 && *r < 1.6), "{ratio:?}");
    c.until(10, "the calibration waits", |a| {
        a.calibrate.pending.is_some()
    })
    .await;
    c.run(Vec::new(), Duration::from_millis(300)).await;
    let s = c.screen();
    assert!(s.contains("hold-out"), "{s}");
    assert!(s.contains("C–R bound"), "{s}");
    assert!(s.contains("× the bound"), "{s}");
    assert!(
        s.contains(&format!("Pending: {out_dir}/calibration.toml")),
        "{s}"
    );
    // Accept, as for any other calibration.
    c.keys(chars("a")).await;
    c.keys(chars("y")).await;
    c.until(10, "in use", |a| {
        a.calibrate
            .active
            .as_ref()
            .is_some_and(|x| x.source.ends_with("calibration.toml"))
            && a.calibrate.pending.is_none()
    })
    .await;
    drop(out);
    rig.stop().await;
}
