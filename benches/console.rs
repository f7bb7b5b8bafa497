//! Console rendering (issue 6, must-show 4: ≤ 5 ms per frame at 160×48): every screen drawn
//! into ratatui's `TestBackend` from the recorded twin session of the render tests
//! (`tests/it/fixtures/console_twin.json`): Live at rest, Measure half-way through a run with
//! its live plot, Results with two runs compared (six charts of both). One iteration is one
//! whole frame drawn from scratch: layout, widgets, and every cell handed to the backend.
//! Run with `cargo bench --bench console`.

use axiscomp::console::app::{Action, App, AppOptions, Field, Screen};
use axiscomp::console::client::{Identity, PeerRole};
use axiscomp::console::ui;
use axiscomp::service::api::Request;
use axiscomp::service::api::snapshot::Snapshot;
use criterion::{Criterion, criterion_group, criterion_main};
use crossterm::event::{KeyCode, KeyEvent, KeyModifiers};
use ratatui::Terminal;
use ratatui::backend::TestBackend;
use serde_json::Value;
use std::collections::VecDeque;
use std::hint::black_box;
use std::time::{Duration, Instant};

const FIXTURE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/it/fixtures/console_twin.json"
);

fn key(c: KeyCode) -> KeyEvent {
    KeyEvent::new(c, KeyModifiers::NONE)
}

/// Answer the app's requests from the recording until it asks no more.
fn answer(app: &mut App, actions: Vec<Action>, now: Instant, fx: &Value, ended: bool) {
    let mut queue: VecDeque<Action> = actions.into();
    while let Some(a) = queue.pop_front() {
        let Action::Send { id, request } = a else {
            continue;
        };
        let mid = fx["mid"].as_u64().expect("mid") as usize;
        let v = match request {
            Request::RunStatus if !ended => {
                let r = &fx["progress"][mid - 1][1]["run"];
                serde_json::json!({"run_id": r["id"], "state": "running",
                    "captures": r["captures"], "expected": r["expected"]})
            }
            Request::RunStatus => fx["finished_status"].clone(),
            Request::RunResult { .. } if !ended => fx["live_result"].clone(),
            Request::RunResult { run_id } if run_id == fx["result_1"]["run"]["id"].as_i64() => {
                fx["result_1"].clone()
            }
            Request::RunResult { .. } => fx["result_2"].clone(),
            Request::Runs { .. } => fx["runs"].clone(),
            Request::TableList { .. } => fx["tables"].clone(),
            Request::TableStatus => fx["table_status"].clone(),
            Request::Calibration => fx["calibration"].clone(),
            other => panic!("unexpected request {other:?}"),
        };
        queue.extend(app.handle_reply(id, Ok(v), now));
    }
}

/// The console after the recorded session: run 2 watched from start to end, the Results
/// screen comparing it with run 1; and the same half-way through run 2 (for Measure).
fn apps(fx: &Value) -> (App, App, App) {
    let t0 = Instant::now();
    let snap = |v: &Value| -> Snapshot { serde_json::from_value(v.clone()).expect("snapshot") };
    let mut app = App::new(
        AppOptions {
            socket: "/run/axiscomp/control.sock".into(),
            jog_step_mm: 0.1,
            color: true,
        },
        t0,
    );
    app.handle_connected(
        Identity {
            user: fx["user"].as_str().map(str::to_string),
            role: Some(PeerRole::Operator),
        },
        t0,
    );
    app.handle_snapshot(snap(&fx["rest"]), t0);
    let rest = app.clone();
    let plan: axiscomp::run::PlanSpec = serde_json::from_value(fx["plan"].clone()).expect("plan");
    app.handle_key(key(KeyCode::Char('4')));
    for f in Field::ALL {
        app.handle_key(key(KeyCode::Enter));
        for _ in 0..16 {
            app.handle_key(key(KeyCode::Backspace));
        }
        for c in f.get(&plan).chars() {
            app.handle_key(key(KeyCode::Char(c)));
        }
        app.handle_key(key(KeyCode::Enter));
        app.handle_key(key(KeyCode::Down));
    }
    app.handle_key(key(KeyCode::Char('s')));
    let start = app.handle_key(key(KeyCode::Char('y')));
    let [Action::Send { id, .. }] = &start[..] else {
        panic!("start: {start:?}")
    };
    app.handle_reply(*id, Ok(fx["start_reply"].clone()), t0);
    let progress = fx["progress"].as_array().expect("progress");
    let mid = fx["mid"].as_u64().expect("mid") as usize;
    let mut now = t0;
    for p in &progress[..mid] {
        now = t0 + Duration::from_secs_f64(p[0].as_f64().expect("time"));
        app.handle_snapshot(snap(&p[1]), now);
    }
    now += Duration::from_millis(500);
    let polls = app.tick(now);
    answer(&mut app, polls, now, fx, false);
    let measure = app.clone();
    for p in &progress[mid..] {
        now = t0 + Duration::from_secs_f64(p[0].as_f64().expect("time"));
        let asks = app.handle_snapshot(snap(&p[1]), now);
        answer(&mut app, asks, now, fx, true);
    }
    let asks = app.handle_key(key(KeyCode::Char('5')));
    answer(&mut app, asks, now, fx, true);
    app.handle_key(key(KeyCode::Down));
    let asks = app.handle_key(key(KeyCode::Char('b')));
    answer(&mut app, asks, now, fx, true);
    assert!(app.results.before.is_some() && app.results.shown.is_some());
    (rest, measure, app)
}

fn bench(c: &mut Criterion) {
    let text = std::fs::read_to_string(FIXTURE).expect("the console fixture");
    let fx: Value = serde_json::from_str(&text).expect("fixture JSON");
    let (rest, measure, results) = apps(&fx);
    // Calibrate and Publish with what they ask for when they show.
    let mut cal = rest.clone();
    let asks = cal.handle_key(key(KeyCode::Char('3')));
    let now = cal.now;
    answer(&mut cal, asks, now, &fx, true);
    assert!(cal.calibrate.pending.is_some());
    let mut publ = results.clone();
    let asks = publ.handle_key(key(KeyCode::Char('6')));
    let now = publ.now;
    answer(&mut publ, asks, now, &fx, true);
    assert!(!publ.publish.tables.is_empty());
    // The published (positioning) table, set against the PLC's.
    while publ.publish.selected_table().map(|t| t.kind.as_str()) != Some("positioning") {
        publ.handle_key(key(KeyCode::Down));
    }
    let mut g = c.benchmark_group("console_160x48");
    g.measurement_time(Duration::from_secs(3));
    g.warm_up_time(Duration::from_secs(1));
    for (screen, state) in [
        (Screen::Live, &rest),
        (Screen::Align, &rest),
        (Screen::Measure, &measure),
        (Screen::Results, &results),
        (Screen::Events, &results),
        (Screen::Calibrate, &cal),
        (Screen::Publish, &publ),
    ] {
        let mut app = state.clone();
        app.screen = screen;
        let mut term = Terminal::new(TestBackend::new(160, 48)).expect("terminal");
        g.bench_function(screen.title().to_lowercase(), |b| {
            b.iter(|| {
                // From scratch: with the previous frame forgotten every cell goes out, the
                // worst case (a screen change, a resize, new data everywhere).
                term.clear().expect("clear");
                term.draw(|f| ui::render(f, black_box(&app))).expect("draw");
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
