//! The console (`axiscomp console`, phase 1).
//!
//! Render tests: every screen at 80×24 and 160×48 into ratatui's `TestBackend`, the buffer's
//! text under insta. The data is a real twin + service run, kept as a fixture
//! (`fixtures/console_twin.json`, made by `capture_console_fixture` below) because a live
//! snapshot's noise digits cannot be rounded away deterministically (a value near a rounding
//! boundary flips between runs). What the fixture redacts: the timestamps are shifted so the
//! first snapshot is at 2026-01-01 08:00:00 UTC (alarm times keep their spacing); nothing else
//! is changed. The key-driven test then runs the real console loop against a live rig and
//! checks every screen's content from live data.

use crate::helpers::{RigOptions, ServiceRig, within_s};
use axiscomp::console::app::{Access, Action, App, AppOptions, LinkState, Screen};
use axiscomp::console::client::{Client, ClientError, ClientOptions, Identity, PeerRole};
use axiscomp::console::{drive, ui};
use axiscomp::run::PlanSpec;
use axiscomp::service::control::Request;
use axiscomp::service::snapshot::Snapshot;
use crossterm::event::{Event, KeyCode, KeyEvent, KeyModifiers};
use futures_util::StreamExt;
use ratatui::Terminal;
use ratatui::backend::TestBackend;
use ratatui::buffer::Buffer;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::{Duration, Instant};

const FIXTURE: &str = "tests/it/fixtures/console_twin.json";

/// Handovers quicker than the production defaults (as in the service tests), so a short run
/// takes about 2.5 s per capture.
const FAST_TRACKING: &str = "[tracking]\nrest_ms = 200\naverage_frames = 100\nsettle_ms = 100\n";

/// The short plan both the fixture and the key-driven test run: 0–10 mm, 5 targets, 2 runs.
fn short_plan() -> PlanSpec {
    PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm: 10.0,
        targets: 5,
        runs: 2,
        overrun_mm: 1.0,
        dwell_s: 2.5,
        feed_mm_min: 3000.0,
        lead_mm: 0.0,
        reference_mm: None,
    }
}

/// A real twin + service session, recorded.
#[derive(Debug, Serialize, Deserialize)]
struct Fixture {
    about: String,
    /// The user the service named in its `status` reply.
    user: String,
    /// At rest at 0 mm after `nominal 0` and `zero`, with PSD3 blocked and unblocked just
    /// before (a cleared `beam-blocked` alarm).
    rest: Snapshot,
    plan: PlanSpec,
    /// The service's reply to `run_start`.
    start_reply: serde_json::Value,
    /// Snapshots while the run went, with seconds since `run_start` was answered.
    progress: Vec<(f64, Snapshot)>,
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
            skip = unicode_width(sym).saturating_sub(1);
            line.push_str(sym);
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out
}

fn unicode_width(s: &str) -> usize {
    ratatui::text::Span::raw(s).width()
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
    use axiscomp::console::app::Field;
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
    app.handle_snapshot(fx.rest.clone(), t0);
    app.tick(t0);
    app
}

/// The app during the run: the plan typed in, started by keys, the service's reply, then the
/// recorded snapshots at their times.
fn run_app(fx: &Fixture, t0: Instant, color: bool) -> App {
    let mut app = rest_app(fx, t0, color);
    for k in chars("4").into_iter().chain(plan_keys(&fx.plan)) {
        assert!(app.handle_key(k).is_empty());
    }
    assert!(app.handle_key(key(KeyCode::Char('s'))).is_empty());
    let Action::Send { id, .. } = app.handle_key(key(KeyCode::Char('y'))).remove(0) else {
        panic!("start sends a request")
    };
    app.handle_reply(id, Ok(fx.start_reply.clone()), t0);
    let mut last = t0;
    for (t, s) in &fx.progress {
        last = t0 + Duration::from_secs_f64(*t);
        app.handle_snapshot(s.clone(), last);
    }
    // The run_status polls the Measure screen makes are answered from the last snapshot.
    let now = last + Duration::from_millis(500);
    for a in app.tick(now) {
        if let Action::Send { id, request } = a {
            assert_eq!(request, Request::RunStatus);
            let r = fx.progress.last().and_then(|(_, s)| s.run.clone()).expect("run");
            app.handle_reply(
                id,
                Ok(serde_json::json!({"run_id": r.id, "state": "running", "captures": r.captures,
                    "expected": r.expected, "missing": r.expected - r.captures, "program": r.program})),
                now,
            );
        }
    }
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
    let t0 = Instant::now();
    let mut rest = rest_app(&fx, t0, true);
    snapshot_screens(&mut rest, &[Screen::Live, Screen::Align, Screen::Calibrate]);
    let mut run = run_app(&fx, t0, true);
    snapshot_screens(
        &mut run,
        &[Screen::Measure, Screen::Results, Screen::Publish, Screen::Events],
    );
}

#[test]
fn overlays_read_only_and_no_service_render() {
    let fx = load_fixture();
    let t0 = Instant::now();
    // Help on the Measure screen.
    let mut app = run_app(&fx, t0, true);
    app.handle_key(key(KeyCode::Char('?')));
    insta::assert_snapshot!("help_measure_80x24", text(&render(&app, 80, 24)));
    // Confirming an abort.
    app.handle_key(key(KeyCode::Esc));
    app.handle_key(key(KeyCode::Char('a')));
    insta::assert_snapshot!("confirm_abort_80x24", text(&render(&app, 80, 24)));
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
    let t0 = Instant::now();
    for color in [true, false] {
        let mut app = run_app(&fx, t0, color);
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
                Instant::now(),
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
        let end = Instant::now() + Duration::from_secs(secs);
        while !pred(&self.app) {
            assert!(
                Instant::now() < end,
                "{what}: not within {secs} s; the screen:\n{}",
                self.screen()
            );
            self.run(Vec::new(), Duration::from_millis(200)).await;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn measure_workflow_by_keys_against_the_twin() {
    let rig = ServiceRig::start(RigOptions {
        service_toml: FAST_TRACKING.into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    let mut c = Console::start(&rig.socket, 80, 24);
    c.until(10, "connected with a snapshot", |a| {
        a.link == LinkState::Up && a.snapshot.is_some()
    })
    .await;
    assert_eq!(c.app.access, Access::Operator, "the status reply names the role");
    assert!(c.screen().contains("Six errors"), "{}", c.screen());
    // Plan: typed into the form on the Measure screen.
    let plan = short_plan();
    let mut keys = chars("4");
    keys.extend(plan_keys(&plan));
    c.keys(keys).await;
    assert_eq!(c.app.plan.spec, plan);
    assert!(c.screen().contains("✓ 20 captures"), "{}", c.screen());
    // Start: asks first, then sends the plan.
    c.keys(chars("s")).await;
    assert!(c.screen().contains("Start the run?"), "{}", c.screen());
    c.keys(chars("y")).await;
    c.until(10, "the run started", |a| a.run.is_some()).await;
    // Progress: captures come in, the ETA appears.
    c.until(120, "three captures", |a| {
        a.run.as_ref().is_some_and(|r| r.captures >= 3)
    })
    .await;
    c.run(Vec::new(), Duration::from_millis(300)).await;
    let r = c.app.run.clone().expect("run");
    assert_eq!(r.expected, Some(20));
    assert!(r.eta().is_some(), "{r:?}");
    let s = c.screen();
    assert!(s.contains(&format!("run {} running", r.run_id)), "{s}");
    assert!(s.contains("ETA"), "{s}");
    assert!(s.contains("run 1  ↑ ■■■"), "{s}");
    // Every screen renders from the live state, at both sizes.
    let mut app = c.app.clone();
    for screen in Screen::ALL {
        app.screen = screen;
        for (w, h) in SIZES {
            let t = text(&render(&app, w, h));
            let expect = match screen {
                Screen::Live => "Six errors",
                Screen::Align => "Beam and centring",
                Screen::Calibrate | Screen::Results | Screen::Publish => "Waits for the control API",
                Screen::Measure => "captures in cycle order",
                Screen::Events => "This console's requests",
            };
            assert!(t.contains(expect), "{screen:?} at {w}×{h}:\n{t}");
        }
    }
    // Abort: asks, sends, and the run ends aborted.
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

/// Record `fixtures/console_twin.json` from a real twin + service run:
/// `cargo test --test it console::capture_console_fixture -- --ignored`, then review the
/// snapshots that change (`INSTA_UPDATE=always` or `cargo insta review`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "writes the fixture; run by hand when the snapshot or the screens change"]
async fn capture_console_fixture() {
    let rig = ServiceRig::start(RigOptions {
        service_toml: FAST_TRACKING.into(),
        twin_cnc: true,
        ..RigOptions::default()
    })
    .await;
    rig.request(Request::Nominal { mm: Some(0.0) })
        .await
        .expect("nominal");
    rig.request(Request::Zero).await.expect("zero");
    rig.twin.plant.set_blocked(2, true);
    rig.wait_for(10, "the beam-blocked alarm", |s| {
        s.alarms.iter().any(|a| a.code == "beam-blocked" && a.active)
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
    let start_reply = rig
        .request(Request::RunStart {
            plan: plan.clone(),
            dialect: None,
            notes: None,
        })
        .await
        .expect("run_start");
    let t0 = Instant::now();
    let mut progress: Vec<(f64, Snapshot)> = Vec::new();
    let mut last = usize::MAX;
    while progress.last().and_then(|(_, s)| s.run.as_ref()).is_none_or(|r| r.captures < 6) {
        assert!(t0.elapsed() < Duration::from_secs(120), "the run stalls");
        let s = rig.snapshot().await;
        if let Some(r) = &s.run
            && r.captures != last
        {
            last = r.captures;
            progress.push((t0.elapsed().as_secs_f64(), s));
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // One more, mid-way to the next capture (the carriage moving or dwelling).
    tokio::time::sleep(Duration::from_millis(1200)).await;
    progress.push((t0.elapsed().as_secs_f64(), rig.snapshot().await));
    rig.request(Request::RunAbort).await.expect("abort");
    // Redaction: shift every timestamp so the rest snapshot is at 2026-01-01 08:00:00 UTC.
    let shift = 1_767_254_400_000_000 - rest.unix_us;
    let redact = |mut s: Snapshot| {
        s.unix_us += shift;
        for a in &mut s.alarms {
            a.since_unix_us += shift;
        }
        s
    };
    let mut start_reply = start_reply;
    // The program's path is in a temporary directory: keep its name only.
    let file = |p: &str| {
        Path::new(p)
            .file_name()
            .map(|f| format!("/var/lib/axiscomp/runs/1/{}", f.to_string_lossy()))
            .unwrap_or_default()
    };
    if let Some(p) = start_reply["program"].as_str() {
        start_reply["program"] = serde_json::Value::String(file(p));
    }
    let fx = Fixture {
        about: "twin + service on loopback (tests/it/console.rs capture_console_fixture): \
                timestamps shifted to 2026-01-01 08:00:00 UTC, program paths moved to \
                /var/lib/axiscomp; everything else as the service sent it"
            .into(),
        user,
        rest: redact(rest),
        plan,
        start_reply,
        progress: progress
            .into_iter()
            .map(|(t, s)| {
                let mut s = redact(s);
                if let Some(r) = &mut s.run {
                    r.program = file(&r.program);
                }
                ((t * 1000.0).round() / 1000.0, s)
            })
            .collect(),
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
